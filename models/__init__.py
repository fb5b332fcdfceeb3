"""The continuous-time model of the elastic string pendulum: the single source of truth.

Public API::

    from reelbench.models import load_scene, build_model
    scene = load_scene("fixed_length", elements=20)
    model = build_model(scene)        # energies, forces, Legendre transform, EOM
    from reelbench.models.diagnostics import evaluate

The model and the scene format are described in models/README.md; the scene schema (keys,
rules, ranges, errors) is `models.schema`; each physical effect (its scene keys, energy terms,
forces) is one `Effect` in models/effects.py, and `register_effect` or an installed package's
``reelbench.effects`` entry point adds one.

The JAX-backed names (`build_model`, `StringPendulum`) are imported on first use, so that
loading and validating a scene (`load_scene`) does not import JAX: the command line refuses
bad input in a fraction of a second. Every module that touches JAX imports `models._jax`
first, which switches JAX to float64 before anything else.
"""

from reelbench.models.effects import Effect, register_effect, unregister_effect
from reelbench.models.schema import SceneChecks
from reelbench.models.layout import StateLayout
from reelbench.models.scene import EFFECTS, Scene, SceneError, available_scenes, load_scene, scene_from_dict

_LAZY = {"StringPendulum": "reelbench.models.model", "build_model": "reelbench.models.model"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'models' has no attribute {name!r}")


__all__ = [
    "EFFECTS",
    "Effect",
    "Scene",
    "SceneChecks",
    "SceneError",
    "StateLayout",
    "StringPendulum",
    "available_scenes",
    "build_model",
    "load_scene",
    "register_effect",
    "scene_from_dict",
    "unregister_effect",
]
