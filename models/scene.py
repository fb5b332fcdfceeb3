"""Scenes: one TOML file fully determines one simulation.

A scene names its physical *effects*; the model builds only the terms those effects need
(`models.model.StringPendulum`). The structural keys are `BASE_SCHEMA`; each effect brings
its own keys and rules (`models.effects.Effect.keys`, `.check`), merged by `schema()`. The file format is described in models/README.md; every
rule listed there is enforced here, before any computation, and every error names the file,
the key and the allowed range (`SceneError`). Magnitudes far outside anything physical
(`PLAUSIBLE`) are refused too, naming the key. No JAX is imported here.

    >>> from models import load_scene
    >>> scene = load_scene("fixed_length", elements=40)
    >>> scene.string.elements
    40
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from models import effects as _effects
from models.effects import Key as _Key

SCENE_DIR = Path(__file__).resolve().parent / "scenes"

#: Every effect a scene may list (name -> `models.effects.Effect`, canonical order). The
#: effects own their scene keys, rules and physics (models/effects.py).
EFFECTS = _effects.EFFECTS


def required_effects() -> tuple[str, ...]:
    """Effects every scene must list (`Effect.required`: elasticity)."""
    return tuple(n for n, e in EFFECTS.items() if e.required)


_VEC3 = "vec3"
_MAT3 = "mat3"


#: The structural keys (owned by no effect). The full schema is these plus every registered
#: effect's own keys (`Effect.keys`), assembled by `schema()`.
BASE_SCHEMA: dict[str, dict[str, _Key] | _Key] = {
    "name": _Key("str", required=True),
    "description": _Key("str", default=""),
    "t_end": _Key("float", "positive", required=True),
    "effects": _Key("effects", required=True),
    "string": {
        "total_length": _Key("float", "positive", required=True),
        "mass_per_length": _Key("float", "positive", required=True),
        "axial_stiffness": _Key("float", "positive", required=True),
        "elements": _Key("int", "at_least_1", required=True),
        "mass_model": _Key("str", "mass_model", default="consistent", hashed_at_default=False),
    },
    "body": {
        "mass": _Key("float", "positive", required=True),
    },
    "reel": {
        "exit_point": _Key(_VEC3, default=(0.0, 0.0, 0.0)),
        "exit_direction": _Key(_VEC3, "nonzero", default=(0.0, 0.0, 1.0)),
        "min_deployed_length": _Key("float", "nonnegative", default=0.0, hashed_at_default=False),
    },
    "initial": {
        "deployed_length": _Key("float", "deployed_length", required=True),
        "direction": _Key(_VEC3, "nonzero", required=True),
        "tip_velocity": _Key(_VEC3, default=(0.0, 0.0, 0.0)),
        "stretch": _Key("float", "stretch", default=1.0, hashed_at_default=False),
    },
    "environment": {
        "g": _Key("float", "nonnegative", default=9.81),
    },
}


def schema() -> dict[str, dict[str, _Key] | _Key]:
    """The whole scene schema: `BASE_SCHEMA` plus the keys of every registered effect (an
    effect's own section, e.g. ``[tip_spring]``, comes after the structural ones)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in BASE_SCHEMA.items()}
    for section, keys in _effects.effect_keys().items():
        if not section:
            out.update(keys)
        else:
            out.setdefault(section, {}).update(keys)
    return out


def plausible_ranges() -> dict[str, tuple[float, float]]:
    """`PLAUSIBLE` plus every registered effect's own ranges (`Effect.plausible`)."""
    out = dict(PLAUSIBLE)
    for e in EFFECTS.values():
        out.update(e.plausible)
    return out

_RULE_TEXT = {
    "finite": "a finite number",
    "positive": "a finite number > 0",
    "nonnegative": "a finite number >= 0",
    "at_least_1": "an integer >= 1",
    "nonzero": "a finite nonzero 3-vector",
    "spd": "a symmetric positive-definite 3x3 matrix (body frame, kg m^2)",
    "rotation": "a 3x3 rotation matrix (orthonormal to 1e-9, det +1)",
    "stretch": f"a finite number in [{1.0 / 100:g}, {100:g}] (stretched / unstretched initial length)",
}

#: Values of `string.mass_model` (MODEL.md §8); the first is the default.
MASS_MODELS = ("consistent", "lumped")
_RULE_TEXT["mass_model"] = "one of " + ", ".join(repr(m) for m in MASS_MODELS)

#: Allowed range of `initial.stretch` (ratio of the initial stretched to unstretched length).
#: 1 = unstretched (the paper's start); < 1 starts compressed (near-slack), > 1 pre-tensioned.
STRETCH_RANGE = (0.01, 100.0)


#: Physically plausible magnitudes, (low, high) of |value| (vectors: of their length), in SI
#: units. Far wider than any real string pendulum, but they stop typos and absurd values
#: (mass 1e300, EA 1e308, a million elements, t_end 1e12 s) before a run overflows, takes
#: days or fills the memory. A value of exactly 0 is judged by the key's own rule. These are the
#: structural keys'; an effect's keys carry their own (`Effect.plausible`, `plausible_ranges()`).
PLAUSIBLE: dict[str, tuple[float, float]] = {
    "t_end": (1e-9, 1e6),
    "string.total_length": (1e-3, 1e5),
    "string.mass_per_length": (1e-9, 1e5),
    "string.axial_stiffness": (1e-6, 1e13),
    "string.elements": (1, 10_000),
    "body.mass": (1e-9, 1e9),
    "reel.exit_point": (0.0, 1e5),
    "initial.tip_velocity": (0.0, 1e4),
    "environment.g": (0.0, 1e4),
}


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


class SceneError(ValueError):
    """A scene file or override is invalid; the message names file, key and allowed range."""


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
    mass_model: str = "consistent"  # string mass matrix, MODEL.md §8 (models.model.STRING_MASS)


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
            raise ValueError(f"unknown effect {effect!r}{_suggest(effect, EFFECTS)}")
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
    (``**{"string.elements": 40}``). Overrides are validated like the file itself.
    """
    if isinstance(name_or_path, Scene):
        return name_or_path.with_(**overrides)
    path = _resolve(name_or_path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text file (not UTF-8): a scene is a TOML file, see models/README.md") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read the scene file ({exc.strerror or exc})") from None
    return _build(data, str(path), overrides)


def scene_from_dict(data: Mapping, source: str = "<dict>", **overrides) -> Scene:
    """Validate a TOML-shaped mapping as a scene (used by tests and generated scenes)."""
    return _build(copy.deepcopy(dict(data)), source, overrides)


def _resolve(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.is_dir():
        raise SceneError(f"{p}: is a directory; give a scene name ({', '.join(available_scenes())}) "
                         f"or the path of a .toml file")
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise SceneError(f"{p}: scene file not found")
        return p
    candidate = SCENE_DIR / f"{name_or_path}.toml"
    if candidate.exists():
        return candidate
    raise SceneError(
        f"unknown scene {str(name_or_path)!r}{_suggest(str(name_or_path), available_scenes())}; "
        f"shipped scenes: {', '.join(available_scenes())}, or give a path to a .toml file"
    )


def _suggest(word: str, options) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.5)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _apply_overrides(data: dict, overrides: Mapping, source: str) -> set[str]:
    """Apply ``overrides`` to ``data`` in place; returns the dotted keys they set."""
    applied: set[str] = set()
    leaf_owner: dict[str, list[str]] = {}
    _SCHEMA = schema()
    for section, spec in _SCHEMA.items():
        if isinstance(spec, dict):
            for key in spec:
                leaf_owner.setdefault(key, []).append(section)
    for name, value in overrides.items():
        if "." in name:
            section, key = name.split(".", 1)
        elif name in _SCHEMA and not isinstance(_SCHEMA[name], dict):
            section, key = None, name
        elif name in leaf_owner:
            section, key = leaf_owner[name][0], name
        else:
            valid = list(leaf_owner) + [k for k, v in _SCHEMA.items() if not isinstance(v, dict)]
            raise SceneError(f"{source}: unknown override {name!r}{_suggest(name, valid)}")
        if section is None:
            data[key] = value
            applied.add(key)
            continue
        if section not in _SCHEMA or not isinstance(_SCHEMA[section], dict) or key not in _SCHEMA[section]:
            raise SceneError(f"{source}: unknown override {name!r}")
        sec = data.setdefault(section, {})
        sec[key] = value
        applied.add(f"{section}.{key}")
        # box and inertia are alternatives: an override of one replaces the other.
        if section == "body" and key in ("box", "inertia"):
            sec.pop("inertia" if key == "box" else "box", None)
    return applied


def _build(data: dict, source: str, overrides: Mapping) -> Scene:
    data = copy.deepcopy(dict(data))
    v = _Validator(source, _apply_overrides(data, overrides, source))
    return v.scene(data)


class _Validator:
    def __init__(self, source: str, overridden: set[str] = frozenset()):
        self.source = source
        self.overridden = overridden  # keys whose value came from an override, not the file
        self.ranges = plausible_ranges()  # the registry's, as it is for this scene

    def _where(self, key: str) -> str:
        return f"{self.source} (overridden)" if key in self.overridden else self.source

    def fail(self, key: str, value: Any, allowed: str) -> SceneError:
        # repr for strings and floats: `mass = "1.0"` must not read as the number 1.0
        shown = repr(value) if isinstance(value, (float, str)) else value
        if isinstance(value, str):
            shown = '"' + value.replace('"', '\\"') + '"'
            allowed += " (a quoted value is a string in TOML: write the number without quotes)" \
                if _looks_numeric(value) else ""
        return SceneError(f"{self._where(key)}: key '{key}' = {shown} is invalid: allowed {allowed}")

    # -- scalar / vector parsing -----------------------------------------------------
    def number(self, key: str, value: Any, rule: str, integer: bool = False) -> float | int:
        allowed = _RULE_TEXT.get(rule, "a finite number")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, value, allowed)
        if not math.isfinite(value):
            raise self.fail(key, value, allowed)
        if integer:
            if isinstance(value, float) and not value.is_integer():
                raise self.fail(key, value, allowed)
            value = int(value)
        else:
            value = float(value)
        if rule == "positive" and not value > 0:
            raise self.fail(key, value, allowed)
        if rule == "nonnegative" and not value >= 0:
            raise self.fail(key, value, allowed)
        if rule == "at_least_1" and not value >= 1:
            raise self.fail(key, value, allowed)
        return value

    def vector(self, key: str, value: Any, rule: str) -> tuple:
        allowed = {"positive": "3 finite numbers > 0", "nonzero": _RULE_TEXT["nonzero"]}.get(
            rule, "3 finite numbers"
        )
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise self.fail(key, value, allowed)
        out = []
        for x in value:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise self.fail(key, value, allowed)
            out.append(float(x))
        if rule == "positive" and not all(x > 0 for x in out):
            raise self.fail(key, value, allowed)
        if rule == "nonzero":
            n = math.sqrt(sum(x * x for x in out))
            if n == 0.0:
                raise self.fail(key, value, allowed)
            out = [x / n for x in out]
        return tuple(out)

    def matrix(self, key: str, value: Any, rule: str) -> tuple:
        allowed = _RULE_TEXT[rule]
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise self.fail(key, value, allowed)
        if not all(isinstance(row, (list, tuple)) and len(row) == 3 for row in value):
            raise self.fail(key, value, allowed)
        rows = [self.vector(key, row, "finite") for row in value]
        m = np.array(rows)
        if rule == "rotation":
            if np.abs(m.T @ m - np.eye(3)).max() > 1e-9 or abs(np.linalg.det(m) - 1.0) > 1e-9:
                raise self.fail(key, value, allowed)
        if rule == "spd":
            if np.abs(m - m.T).max() > 1e-12 * max(1.0, np.abs(m).max()) or np.linalg.eigvalsh(m).min() <= 0:
                raise self.fail(key, value, allowed)
        return tuple(tuple(float(x) for x in row) for row in rows)

    # -- the whole scene ---------------------------------------------------------------
    def scene(self, data: dict) -> Scene:
        effects = self.effects(data.get("effects"))
        _SCHEMA = schema()
        for key in data:
            if key not in _SCHEMA:
                raise SceneError(
                    f"{self.source}: unknown key '{key}'{_suggest(key, _SCHEMA)}; "
                    f"allowed top-level keys: {', '.join(_SCHEMA)}"
                )
        out: dict[str, Any] = {}
        for key, spec in _SCHEMA.items():
            if isinstance(spec, dict):
                section = data.get(key, {})
                if not isinstance(section, dict):
                    raise self.fail(key, section, "a table of keys")
                out[key] = self.section(key, section, spec, effects)
            else:
                out[key] = self.value(key, data.get(key), spec, effects)
        out["effects"] = list(effects)
        return self.cross_checks(out, effects)

    def effects(self, value: Any) -> tuple[str, ...]:
        if value is None:
            raise SceneError(f"{self.source}: missing key 'effects' (allowed: a list of {', '.join(EFFECTS)})")
        if not isinstance(value, (list, tuple)) or not all(isinstance(e, str) for e in value):
            raise self.fail("effects", value, f"a list of effect names from {', '.join(EFFECTS)}")
        for e in value:
            if e not in EFFECTS:
                raise SceneError(
                    f"{self.source}: key 'effects' has unknown effect {e!r}{_suggest(e, EFFECTS)}; "
                    f"allowed: {', '.join(EFFECTS)}"
                )
        if len(set(value)) != len(value):
            raise self.fail("effects", value, "each effect listed once")
        for e in value:
            for need in EFFECTS[e].needs:
                if need not in value:
                    raise SceneError(f"{self.source}: key 'effects': effect {e!r} needs effect {need!r} in the list")
        for need in required_effects():
            if need not in value:
                raise SceneError(f"{self.source}: key 'effects' must include {need!r} (a string needs it)")
        # canonical order: the order of EFFECTS
        return tuple(e for e in EFFECTS if e in value)

    def section(self, name: str, section: dict, spec: dict[str, _Key], effects) -> dict:
        for key in section:
            if key not in spec:
                raise SceneError(
                    f"{self.source}: unknown key '{name}.{key}'{_suggest(key, spec)}; "
                    f"allowed in [{name}]: {', '.join(spec)}"
                )
        out = {}
        for key, s in spec.items():
            if s.only_with_effect:
                listed = all(e in effects for e in s.required_by)
                if not listed and section.get(key) is not None:
                    raise SceneError(
                        f"{self.source}: key '{name}.{key}' = {section[key]!r} is only allowed with effect "
                        f"{', '.join(repr(e) for e in s.required_by)} in the list 'effects'"
                    )
                if not listed:
                    continue
            out[key] = self.value(f"{name}.{key}", section.get(key), s, effects)
        return out

    def value(self, key: str, value: Any, spec: _Key, effects) -> Any:
        out = self._value(key, value, spec, effects)
        if key in self.ranges and value is not None:
            self.plausible(key, value, out)
        return out

    def plausible(self, key: str, raw: Any, value: Any) -> None:
        lo, hi = self.ranges[key]
        if isinstance(raw, (list, tuple)):  # a vector: its length (nonzero rules normalise `value`)
            mag = math.sqrt(sum(float(x) ** 2 for x in raw))
        else:
            mag = abs(float(value))
        if mag != 0.0 and not lo <= mag <= hi:
            raise SceneError(
                f"{self._where(key)}: key '{key}' = {raw!r} is implausible: allowed a magnitude in [{lo:g}, {hi:g}] "
                f"(SI units; see models/README.md). Check the units and the exponent")

    def _value(self, key: str, value: Any, spec: _Key, effects) -> Any:
        if value is None:
            needed = spec.required or (spec.required_by is not None and all(e in effects for e in spec.required_by))
            if needed:
                why = f" (needed by effect {', '.join(spec.required_by)})" if spec.required_by else ""
                allowed = "a string" if spec.kind == "str" else _RULE_TEXT.get(spec.rule, spec.kind)
                raise SceneError(f"{self.source}: missing key '{key}'{why}: allowed {allowed}")
            return copy.deepcopy(spec.default)
        if (spec.required_by is not None and not all(e in effects for e in spec.required_by)
                and spec.default is not None and value == spec.default):
            # the default of a key whose effect is not listed, as `Scene.to_dict` writes it back
            # for a file without that key: `with_` must accept the scene it was given (a reel
            # key's default, e.g. guide_length = 0, need not meet the rule it has with a reel)
            return copy.deepcopy(spec.default)
        if spec.kind == "str":
            if spec.rule == "mass_model" and value not in MASS_MODELS:
                raise self.fail(key, repr(value), _RULE_TEXT["mass_model"])
            if not isinstance(value, str):
                raise self.fail(key, value, "a string")
            return value
        if spec.kind == "effects":
            return list(value)
        if spec.kind == "float":
            if spec.rule == "deployed_length":
                return self.number(key, value, "positive")
            if spec.rule == "stretch":
                v = self.number(key, value, "stretch")
                if not STRETCH_RANGE[0] <= v <= STRETCH_RANGE[1]:
                    raise self.fail(key, value, _RULE_TEXT["stretch"])
                return v
            return self.number(key, value, spec.rule)
        if spec.kind == "int":
            return self.number(key, value, spec.rule, integer=True)
        if spec.kind == _VEC3:
            return list(self.vector(key, value, spec.rule))
        if spec.kind == _MAT3:
            return [list(r) for r in self.matrix(key, value, spec.rule)]
        raise AssertionError(spec.kind)

    def cross_checks(self, d: dict, effects: tuple[str, ...]) -> Scene:
        s, b, r, i = d["string"], d["body"], d["reel"], d["initial"]
        L, guide = s["total_length"], r["guide_length"]
        if not i["deployed_length"] < L - guide:
            raise SceneError(
                f"{self.source}: key 'initial.deployed_length' = {i['deployed_length']!r} is invalid: "
                f"allowed 0 < deployed_length < total_length - guide_length = {L - guide!r}"
            )
        if not r["min_deployed_length"] < i["deployed_length"]:
            raise SceneError(
                f"{self.source}: key 'reel.min_deployed_length' = {r['min_deployed_length']!r} is invalid: "
                f"allowed 0 <= min_deployed_length < initial.deployed_length = {i['deployed_length']!r}"
            )
        # each effect's own rules (listed or not: e.g. Ω must be 0 without `rigid_body`)
        for effect in EFFECTS.values():
            effect.check(self, d, effects)
        if b["box"] is not None:
            a, bb, c = b["box"]
            m = b["mass"]
            inertia = np.diag([m / 12 * (bb * bb + c * c), m / 12 * (a * a + c * c), m / 12 * (a * a + bb * bb)])
        elif b["inertia"] is not None:
            inertia = np.array(b["inertia"])
        else:
            inertia = np.zeros((3, 3))
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
            source=self.source,
            raw=raw,
        )
