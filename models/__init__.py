"""The continuous-time model of the elastic string pendulum: the single source of truth.

Public API::

    from models import load_scene, build_model
    scene = load_scene("fixed_length", elements=20)
    model = build_model(scene)        # energies, forces, Legendre transform, EOM
    from models.diagnostics import evaluate
"""

from models import _jax  # noqa: F401  (float64 before anything else touches JAX)
from models.layout import StateLayout
from models.model import StringPendulum, build_model
from models.scene import EFFECTS, Scene, SceneError, available_scenes, load_scene, scene_from_dict

__all__ = [
    "EFFECTS",
    "Scene",
    "SceneError",
    "StateLayout",
    "StringPendulum",
    "available_scenes",
    "build_model",
    "load_scene",
    "scene_from_dict",
]
