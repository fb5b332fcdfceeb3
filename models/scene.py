"""Scenes: one TOML file fully determines one simulation.

A scene names its physical *effects*; the model builds only the terms those effects need
(`models.model.StringPendulum`). The keys, their rules and plausible ranges are the schema's
(`models.schema`: the structural `BASE_SCHEMA` plus each effect's `Effect.keys`); this module
reads the file, applies overrides and builds the immutable `Scene`. The file format is
described in models/README.md; every rule listed there is enforced before any computation,
and every error is a `SceneError` naming the file, the key and the allowed range. A scene
file is read only if it is a regular file of at most `MAX_SCENE_BYTES` (`models.io`). No JAX
is imported here.

    >>> from reelbench.models import load_scene
    >>> scene = load_scene("fixed_length", elements=40)
    >>> scene.string.elements
    40
"""

from __future__ import annotations

import codecs
import copy
import dataclasses
import hashlib
import json
import os
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from reelbench.models import effects as _effects
from reelbench.models import io as _io
from reelbench.models.effects import EFFECTS, body_inertia
from reelbench.models.schema import (BASE_SCHEMA, MASS_MODELS, MAX_DEPTH, NESTED_TOO_DEEPLY, PLAUSIBLE, STRETCH_RANGE,
                           SceneError, Validator, full_schema, is_safe_name, nesting_depth, suggest, too_deep)
from reelbench.models.schema import plausible_ranges as _plausible_ranges

__all__ = ["BASE_SCHEMA", "EFFECTS", "MASS_MODELS", "MAX_SCENE_BYTES", "PLAUSIBLE", "SCENE_DIR", "STRETCH_RANGE",
           "Scene", "SceneError", "available_scenes", "load_scene", "plausible_ranges", "required_effects",
           "scene_from_dict", "schema"]

SCENE_DIR = Path(__file__).resolve().parent / "scenes"

#: Largest scene file read, bytes (a scene is about 2 kB; a bigger file is refused unread).
MAX_SCENE_BYTES = 1_000_000


def required_effects() -> tuple[str, ...]:
    """Effects every scene must list (`Effect.required`: elasticity)."""
    return tuple(n for n, e in EFFECTS.items() if e.required)


def schema():
    """The whole scene schema: `BASE_SCHEMA` plus the keys of every registered effect."""
    return full_schema(EFFECTS)


def plausible_ranges() -> dict[str, tuple[float, float]]:
    """`PLAUSIBLE` plus every registered effect's own ranges (`Effect.plausible`)."""
    return _plausible_ranges(EFFECTS)


# --------------------------------------------------------------------------------------------
# Validated scene
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StringParams:
    total_length: float  # L
    mass_per_length: float  # mu
    axial_stiffness: float  # EA
    elements: int  # N
    axial_damping: float | None = None  # c, N s (only with effect `axial_damping`)
    mass_model: str = "consistent"  # the string's element mass matrix (models.model.STRING_MASS)
    # the fluid's string keys, out of the repr (a scene without them reads as before they existed;
    # `Scene.raw` holds them for the key and the comparison)
    diameter: float | None = dataclasses.field(default=None, repr=False)  # d, m (only with `buoyancy`)
    normal_drag: float | None = dataclasses.field(default=None, repr=False)  # C_n (only with `drag`)
    tangential_drag: float | None = dataclasses.field(default=None, repr=False)  # C_t (only with `drag`)


@dataclass(frozen=True)
class BodyParams:
    mass: float  # m_b
    inertia: tuple  # J_c about the CoM, body frame, 3x3 nested tuple
    attachment_to_com: tuple  # rho_c, body frame


@dataclass(frozen=True)
class ReelParams:
    radius: float  # d
    center: tuple  # r_d
    guide_length: float  # b
    equivalent_mass: float  # kappa_d
    exit_point: tuple  # r_p
    exit_direction: tuple  # t_g (unit)
    control_moment: float  # u
    min_deployed_length: float = 0.0  # lower end of the deployed length's range (retrieval stops there)


@dataclass(frozen=True)
class InitialState:
    deployed_length: float
    direction: tuple  # unit
    reel_rate: float
    tip_velocity: tuple
    attitude: tuple  # 3x3 nested tuple
    angular_velocity: tuple
    stretch: float = 1.0  # initial stretched / unstretched length of every element


@dataclass(frozen=True)
class Scene:
    """A validated, immutable scene. Build with `load_scene`; change with `scene.with_(...)`."""

    name: str
    description: str
    t_end: float
    effects: tuple[str, ...]
    string: StringParams
    body: BodyParams
    reel: ReelParams
    initial: InitialState
    g: float
    source: str = dataclasses.field(default="<memory>", compare=False)
    # compared and hashed: an effect's own section (e.g. [tip_spring]) lives only here, and
    # caches keyed by the scene (`build_model`) must tell two such scenes apart
    raw: str = dataclasses.field(default="{}", repr=False)

    def has(self, effect: str) -> bool:
        if effect not in EFFECTS:
            _effects.ensure_known([effect])
        if effect not in EFFECTS:
            raise ValueError(f"unknown effect {effect!r}{suggest(effect, EFFECTS)}")
        return effect in self.effects

    def to_dict(self) -> dict:
        """The scene as a TOML-shaped dict (validated values, defaults filled in)."""
        return json.loads(self.raw)

    def section(self, name: str) -> dict:
        """The validated keys of one section, e.g. an effect's own ``[tip_spring]`` ({} if absent)."""
        return self.to_dict().get(name, {})

    def key(self) -> str:
        """A hash of everything that determines the simulation (not name/description)."""
        d = self.to_dict()
        d.pop("name", None)
        d.pop("description", None)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]

    def with_(self, **overrides) -> "Scene":
        """A copy with overrides applied and re-validated (same keywords as `load_scene`)."""
        return _build(self.to_dict(), self.source, overrides)

    # Convenience numpy views -----------------------------------------------------------
    @property
    def inertia(self) -> np.ndarray:
        return np.array(self.body.inertia, dtype=float)


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def available_scenes() -> list[str]:
    """Names of the scenes shipped with the package."""
    return sorted(p.stem for p in SCENE_DIR.glob("*.toml"))


def load_scene(name_or_path: str | Path | Scene, **overrides) -> Scene:
    """Load a scene by shipped name (e.g. ``"fixed_length"``) or path, apply overrides.

    Overrides are keyword arguments named after a scene key, either its bare name when that
    is unambiguous (``elements=40``, ``t_end=2.0``, ``control_moment=5``) or its dotted path
    (``**{"string.elements": 40}``). Overrides are validated like the file itself; an
    override of ``effects`` drops the keys of the effects it removes.
    """
    if isinstance(name_or_path, Scene):
        return name_or_path.with_(**overrides)
    path = _resolve(name_or_path)
    return _build(_read(path), str(path), overrides)


def scene_from_dict(data: Mapping, source: str = "<dict>", **overrides) -> Scene:
    """Validate a TOML-shaped mapping as a scene (used by tests and generated scenes)."""
    return _build(data, source, overrides)


def _resolve(name_or_path: str | Path) -> Path:
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise SceneError(f"a scene is given by name or path, not {type(name_or_path).__name__} {name_or_path!r}")
    text = os.fspath(name_or_path)
    if isinstance(text, bytes) or "\0" in text or not _encodable(text):
        raise SceneError(f"{text!r} is not a scene name or a path: a path is text without NUL bytes that the "
                         f"file system can encode")
    if text.endswith(".toml") or os.path.lexists(text):
        return Path(text)  # a path: `_read` says what is wrong with it, if anything
    candidate = SCENE_DIR / f"{text}.toml"
    if is_safe_name(text) and candidate.is_file():
        return candidate
    raise SceneError(
        f"unknown scene {text!r}{suggest(text, available_scenes())}; "
        f"shipped scenes: {', '.join(available_scenes())}, or give a path to a .toml file"
    )


def _encodable(text: str) -> bool:
    try:
        os.fsencode(text)  # an unpaired surrogate (from a JSON \ud800 escape) names no file
        return True
    except UnicodeError:
        return False


def _read(path: Path) -> dict:
    """The TOML of a scene file, refused with a `SceneError` naming the file and the fix."""
    try:
        raw = _io.read_regular_file(path, MAX_SCENE_BYTES)
    except _io.FileRefused as exc:
        if exc.kind == "directory":
            raise SceneError(f"{path}: is a directory; give a scene name ({', '.join(available_scenes())}) "
                             f"or the path of a .toml file") from None
        what = "scene file not found" if str(exc) == "not found" else f"{exc}"
        hint = "; a scene is a TOML file of a few kB (see models/README.md)" if exc.kind == "too_large" else ""
        raise SceneError(f"{path}: {what}{hint}") from None
    if raw.startswith(codecs.BOM_UTF8):
        raw = raw[len(codecs.BOM_UTF8):]  # written by some editors; TOML itself has no BOM
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text file (not UTF-8): a scene is a TOML file, see models/README.md") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:  # arrays or inline tables nested hundreds deep
        raise SceneError(f"{path}: {NESTED_TOO_DEEPLY}") from None
    except ValueError:  # an integer of more digits than Python converts (int_max_str_digits)
        raise SceneError(f"{path}: not a scene: an integer in it has more than {sys.get_int_max_str_digits()} "
                         f"digits; a scene's values are finite numbers of a plausible size") from None


def _apply_overrides(data: dict, overrides: Mapping, source: str) -> set[str]:
    """Apply ``overrides`` to ``data`` in place; returns the dotted keys they set.

    ``effects`` is applied first, and drops the keys of the effects it removes (which would
    otherwise be refused as belonging to an effect not listed).
    """
    applied: set[str] = set()
    full = schema()
    leaf_owner: dict[str, list[str]] = {}
    for section, spec in full.items():
        if isinstance(spec, dict):
            for key in spec:
                leaf_owner.setdefault(key, []).append(section)
    for name, value in sorted(overrides.items(), key=lambda kv: kv[0] != "effects"):
        if "." in name:
            section, key = name.split(".", 1)
        elif name in full and not isinstance(full[name], dict):
            section, key = None, name
        elif name in leaf_owner:
            section, key = leaf_owner[name][0], name
        else:
            valid = list(leaf_owner) + [k for k, v in full.items() if not isinstance(v, dict)]
            raise SceneError(f"{source}: unknown override {name!r}{suggest(name, valid)}; allowed: a key of the scene "
                             "format (models/README.md), e.g. elements, mass, t_end, or SECTION.KEY")
        if section is None:
            if key == "effects":
                _drop_keys_of_removed_effects(data, value)
            data[key] = value
            applied.add(key)
            continue
        if section not in full or not isinstance(full[section], dict) or key not in full[section]:
            dotted = [f"{sec}.{k}" for sec, spec in full.items() if isinstance(spec, dict) for k in spec]
            raise SceneError(f"{source}: unknown override {name!r}{suggest(name, dotted)}; allowed: SECTION.KEY of the "
                             "scene format (models/README.md), e.g. string.elements")
        sec = data.setdefault(section, {})
        if not isinstance(sec, dict):
            raise SceneError(f"{source}: key '{section}' is not a table, so '{name}' cannot be overridden")
        sec[key] = value
        applied.add(f"{section}.{key}")
        # box and inertia are alternatives: an override of one replaces the other.
        if section == "body" and key in ("box", "inertia"):
            sec.pop("inertia" if key == "box" else "box", None)
    return applied


def _drop_keys_of_removed_effects(data: dict, new: Any) -> None:
    old = data.get("effects")
    if not (isinstance(old, list) and isinstance(new, (list, tuple))):
        return  # the validation of `effects` reports what is wrong
    # names only: a list such as [[1.0, 2.0], [3.0]] is unhashable, and validation refuses it
    removed = {e for e in old if isinstance(e, str)} - {e for e in new if isinstance(e, str)}
    for name in removed:
        effect = EFFECTS.get(name) if isinstance(name, str) else None
        for section, keys in (effect.keys.items() if effect else ()):
            table = data.get(section) if section else data
            if isinstance(table, dict):
                for key, spec in keys.items():
                    if not spec.kept_without_effect:
                        table.pop(key, None)


def _build(data: Mapping, source: str, overrides: Mapping) -> Scene:
    if not isinstance(data, Mapping):
        raise SceneError(f"{source}: a scene is a table of keys, not {type(data).__name__}")
    # before anything walks them recursively (deepcopy, json)
    for name, part in overrides.items():
        if nesting_depth(part) > MAX_DEPTH:
            raise SceneError(f"{source}: override {name!r} is {NESTED_TOO_DEEPLY}")
    if nesting_depth(data) > MAX_DEPTH:
        deep = too_deep(data)
        raise SceneError(f"{source}: key {deep!r} is {NESTED_TOO_DEEPLY}" if deep else f"{source}: {NESTED_TOO_DEEPLY}")
    data = copy.deepcopy(dict(data))
    listed = [e for part in (data.get("effects"), overrides.get("effects")) if isinstance(part, (list, tuple))
              for e in part]
    _effects.ensure_known(listed)  # the entry-point plugins (once per process)
    overridden = _apply_overrides(data, overrides, source)
    values, effects = Validator(source, overridden, EFFECTS, _effects.unusable()).validate(data)
    return _scene_of(values, effects, source)


def _scene_of(d: dict, effects: tuple[str, ...], source: str) -> Scene:
    """The `Scene` of a validated dict (`models.schema.Validator.validate`)."""
    s, b, r, i = d["string"], d["body"], d["reel"], d["initial"]
    inertia = body_inertia(b)
    raw_d = {k: v for k, v in d.items() if v is not None}
    for section, spec in schema().items():
        if not isinstance(spec, dict) or section not in raw_d:
            continue
        # keys added later are left out at their defaults, so that existing scenes keep their key()
        raw_d[section] = {k: v for k, v in raw_d[section].items()
                          if not (k in spec and not spec[k].hashed_at_default and v == spec[k].default)}
        if not raw_d[section] and section not in BASE_SCHEMA:
            del raw_d[section]  # an effect's own section, without its effect: not part of the physics
    raw = json.dumps(raw_d, sort_keys=True)
    return Scene(
        name=d["name"],
        description=d["description"],
        t_end=d["t_end"],
        effects=effects,
        string=StringParams(**s),
        body=BodyParams(
            mass=b["mass"],
            inertia=tuple(tuple(float(x) for x in row) for row in inertia),
            attachment_to_com=tuple(b["attachment_to_com"]),
        ),
        reel=ReelParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in r.items()}),
        initial=InitialState(
            deployed_length=i["deployed_length"],
            direction=tuple(i["direction"]),
            reel_rate=i["reel_rate"],
            tip_velocity=tuple(i["tip_velocity"]),
            attitude=tuple(tuple(row) for row in i["attitude"]),
            angular_velocity=tuple(i["angular_velocity"]),
            stretch=i["stretch"],
        ),
        g=d["environment"]["g"],
        source=source,
        raw=raw,
    )
