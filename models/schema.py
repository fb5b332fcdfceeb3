"""The scene schema, in one place: every key, its rule, its plausible range and its error.

`BASE_SCHEMA` holds the structural keys; each effect brings its own (`Effect.keys`) and the
full schema is both (`full_schema`). `validate` turns a TOML-shaped mapping into the dict of
validated values, refusing anything outside the rules with a `SceneError` that names the
file, the key, the value as given and what is allowed. An effect's own cross-checks
(`Effect.check`) receive a `SceneChecks`, the public way to refuse a scene.

This module imports nothing else from `models` (the effect registry is passed in) and no JAX:
the command line validates scenes before it loads the physics.
"""

from __future__ import annotations

import difflib
import math
import re
import unicodedata
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np


class SceneError(ValueError):
    """A scene file or override is invalid; the message names file, key and allowed range.

    The message is one printable line whatever the input held: control characters, line
    breaks and unpaired surrogates (in a file name, a key, a value) are written as \\uXXXX."""

    def __init__(self, message: str):
        super().__init__(_escaped(str(message)))


@dataclass(frozen=True)
class Key:
    """Schema entry of one scene key: type, constraint and default."""

    kind: str  # "float", "int", "str", "vec3", "mat3", "effects"
    rule: str = "finite"  # "finite", "positive", "nonnegative", "nonzero", ...
    default: Any = None
    required_by: tuple[str, ...] | None = None  # required iff all these effects are listed
    required: bool = False
    # A key that exists only for its effect (`required_by`): refused without it, and left out
    # of the validated dict (hence of `Scene.key()`) when absent, so scenes without the
    # effect keep their hash.
    only_with_effect: bool = False
    # A key added after results were keyed: left out of `Scene.key()` at its default, so
    # that existing scenes keep their key.
    hashed_at_default: bool = True
    # Accepted with any valid value while its effect is not listed. Otherwise a key an effect
    # owns must keep its default without that effect (a value there would be silently ignored).
    # Only the reel's geometry is: it describes the machine the string hangs from, which a
    # fixed-length scene may describe too (its guide length bounds the deployed length).
    kept_without_effect: bool = False


# --------------------------------------------------------------------------------------------
# Rules and ranges
# --------------------------------------------------------------------------------------------

#: A scene name becomes part of file names (figures, cached references, trajectories), so it
#: is data, never a path: letters, digits, '_', '.', '-', starting with a letter or digit.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
NAME_RULE = ("1 to 64 characters from A-Z a-z 0-9 _ . - , starting with a letter or a digit, "
             "without '..' (the name becomes part of file names)")
#: `description` is one line of a table.
MAX_DESCRIPTION = 500
#: Items of a list or table a message shows before it says how many there are.
MAX_SHOWN_ITEMS = 9

#: Values of `string.mass_model`; the first is the default.
MASS_MODELS = ("consistent", "lumped")
#: Allowed range of `initial.stretch` (ratio of the initial stretched to unstretched length).
#: 1 = unstretched (the paper's start); < 1 starts compressed (near-slack), > 1 pre-tensioned.
STRETCH_RANGE = (0.01, 100.0)
#: Shortest unstretched element at the start, m: the shortest string `string.total_length`
#: admits. An element's axial period is about l·sqrt(μ/EA); at l -> 0 it vanishes, a solver
#: takes steps without end and the squared node offsets underflow (1e-300 m gives a Newton
#: failure at the first step and a reference solve that never ends).
MIN_ELEMENT_LENGTH = 1e-3
#: Lengths a direction vector may have before it is normalised. The length itself carries no
#: meaning, but one far outside is a typo, and near the ends of float64 the "unit" vector is
#: made of rounding (subnormal entries) or its length overflows (`Validator.direction`
#: computes it without squaring and names an overflow).
DIRECTION_LENGTH = (1e-150, 1e150)
#: Radius of gyration sqrt(J/m_b) of every principal moment of the body's inertia, m: the
#: span of the body sizes `body.box` admits (a 1e-6 m cube has 4e-7 m, a 1e4 m one 4e3 m).
GYRATION_RADIUS = (1e-7, 1e4)

RULE_TEXT = {
    "finite": "a finite number",
    "positive": "a finite number > 0",
    "nonnegative": "a finite number >= 0",
    "at_least_1": "an integer >= 1",
    "nonzero": f"a nonzero 3-vector of finite numbers whose length is in [{DIRECTION_LENGTH[0]:g}, "
               f"{DIRECTION_LENGTH[1]:g}] (it is normalised on load)",
    "spd": "a symmetric positive-definite 3x3 matrix (body frame, kg m^2)",
    "rotation": "a 3x3 rotation matrix (orthonormal to 1e-9, det +1)",
    "stretch": f"a finite number in [{STRETCH_RANGE[0]:g}, {STRETCH_RANGE[1]:g}] "
               f"(stretched / unstretched initial length)",
    "mass_model": "one of " + ", ".join(repr(m) for m in MASS_MODELS),
    "name": NAME_RULE,
    "line": f"one line of at most {MAX_DESCRIPTION} characters, without control characters, line breaks or "
            f"unpaired surrogates",
}

#: The structural keys (owned by no effect). The full schema is these plus every registered
#: effect's own keys (`Effect.keys`), assembled by `full_schema`.
BASE_SCHEMA: dict[str, dict[str, Key] | Key] = {
    "name": Key("str", "name", required=True),
    "description": Key("str", "line", default=""),
    "t_end": Key("float", "positive", required=True),
    "effects": Key("effects", required=True),
    "string": {
        "total_length": Key("float", "positive", required=True),
        "mass_per_length": Key("float", "positive", required=True),
        "axial_stiffness": Key("float", "positive", required=True),
        "elements": Key("int", "at_least_1", required=True),
        "mass_model": Key("str", "mass_model", default="consistent", hashed_at_default=False),
    },
    "body": {
        "mass": Key("float", "positive", required=True),
    },
    "reel": {
        "exit_point": Key("vec3", default=(0.0, 0.0, 0.0)),
        "exit_direction": Key("vec3", "nonzero", default=(0.0, 0.0, 1.0)),
        "min_deployed_length": Key("float", "nonnegative", default=0.0, hashed_at_default=False),
    },
    "initial": {
        "deployed_length": Key("float", "positive", required=True),
        "direction": Key("vec3", "nonzero", required=True),
        "tip_velocity": Key("vec3", default=(0.0, 0.0, 0.0)),
        "stretch": Key("float", "stretch", default=1.0, hashed_at_default=False),
    },
    "environment": {
        "g": Key("float", "nonnegative", default=9.81),
    },
}

#: Physically plausible magnitudes, (low, high) of |value| (vectors: of their length), in SI
#: units. Far wider than any real string pendulum, but they stop typos and absurd values
#: (mass 1e300, EA 1e308, a million elements, t_end 1e12 s) before a run overflows, takes
#: days or fills the memory. A value of exactly 0 is judged by the key's own rule. These are the
#: structural keys'; an effect's keys carry their own (`Effect.plausible`, `plausible_ranges`).
#: The deployed length, the directions, the stretch and the inertia have rules of their own
#: (`MIN_ELEMENT_LENGTH`, `DIRECTION_LENGTH`, `STRETCH_RANGE`, `GYRATION_RADIUS`).
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

#: Deepest nesting of tables and arrays a scene has (top level, section, matrix, row); a file
#: nested deeper is refused before anything walks it.
MAX_DEPTH = 4
NESTED_TOO_DEEPLY = (f"nested too deeply: a scene has at most {MAX_DEPTH} levels of tables and arrays "
                     f"(top level, section, matrix, row); see models/README.md for the format")


def full_schema(registry: Mapping) -> dict[str, dict[str, Key] | Key]:
    """`BASE_SCHEMA` plus the keys of every effect in ``registry`` (name -> `Effect`); an
    effect's own section, e.g. ``[tip_spring]``, comes after the structural ones."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in BASE_SCHEMA.items()}
    for effect in registry.values():
        for section, keys in effect.keys.items():
            if not section:
                out.update(keys)
            else:
                out.setdefault(section, {}).update(keys)
    return out


def plausible_ranges(registry: Mapping) -> dict[str, tuple[float, float]]:
    """`PLAUSIBLE` plus every registered effect's own ranges (`Effect.plausible`)."""
    out = dict(PLAUSIBLE)
    for effect in registry.values():
        out.update(effect.plausible)
    return out


def key_owners(registry: Mapping) -> dict[str, str]:
    """{dotted key: name of the effect that owns it} (top-level keys without a dot)."""
    return {(f"{section}.{key}" if section else key): effect.name
            for effect in registry.values() for section, keys in effect.keys.items() for key in keys}


def is_safe_name(text: Any) -> bool:
    """A scene name by `NAME_PATTERN`: safe as part of a file name on every platform we run on."""
    return isinstance(text, str) and NAME_PATTERN.fullmatch(text) is not None and ".." not in text


def nesting_depth(value: Any) -> int:
    """Levels of dicts and lists in ``value`` (0 for a scalar), found without recursion."""
    deepest, todo = 0, [(value, 1)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, dict):
            children = item.values()
        elif isinstance(item, (list, tuple)):
            children = item
        else:
            continue
        deepest = max(deepest, depth)
        if depth > MAX_DEPTH:
            return depth  # deep enough to refuse: do not walk 2,000 levels
        todo.extend((child, depth + 1) for child in children)
    return deepest


def too_deep(data: Mapping) -> str | None:
    """The dotted key of the first entry of a scene mapping nested beyond `MAX_DEPTH` (None: the
    mapping itself is, e.g. a table in a section's table)."""
    for key, value in data.items():
        if isinstance(value, dict):
            for sub, item in value.items():
                if nesting_depth(item) > MAX_DEPTH - 2:
                    return f"{key}.{sub}"
        elif nesting_depth(value) > MAX_DEPTH - 1:
            return str(key)
    return None


def suggest(word: str, options) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.5)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _finite_number(x: Any) -> bool:
    """A finite int or float (not a bool); integers beyond 2**53 are refused: they have no exact
    float, and beyond 1e308 none at all (converting them raises)."""
    if isinstance(x, bool):
        return False
    if isinstance(x, int):
        return abs(x) <= 2**53
    return isinstance(x, float) and math.isfinite(x)


def vector_length(values) -> float:
    """Euclidean length of finite numbers without overflow or underflow in the squares
    (`math.hypot` scales before squaring): inf only when the length itself exceeds the largest
    float64, never an OverflowError ([-1e308, 0, 0] has length 1e308)."""
    return math.hypot(*(float(x) for x in values))


def _flat_numbers(value: Any) -> list:
    """The numbers of a validated vector or matrix, row by row."""
    if isinstance(value, (list, tuple)):
        return [x for item in value for x in _flat_numbers(item)]
    return [value]


def _is_plain_data(value: Any) -> bool:
    """Built of str, bool, int, float, list, tuple and dict only (what TOML, JSON and --set
    give): only such values are compared with a default (a numpy array's == has no truth value)."""
    todo = [value]
    while todo:
        item = todo.pop()
        if isinstance(item, (list, tuple)):
            todo.extend(item)
        elif isinstance(item, dict):
            todo.extend(item.values())
        elif type(item) not in (str, bool, int, float):
            return False
    return True


def _is_default(value: Any, default: Any) -> bool:
    return default is not None and _is_plain_data(value) and value == _plain(default)


def _plain(value: Any) -> Any:
    """A default as the validated dict holds it (tuples as lists, as TOML and JSON have them)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


#: Characters a message never holds as they are: control characters and line breaks would
#: split its one line, an unpaired surrogate cannot be written as UTF-8.
_UNPRINTABLE = ("Cc", "Cs", "Zl", "Zp")


def _escaped(text: str) -> str:
    """``text`` with `_UNPRINTABLE` characters written as TOML's \\uXXXX escapes."""
    return "".join(f"\\u{ord(c):04x}" if unicodedata.category(c) in _UNPRINTABLE else c for c in text)


def shown(value: Any) -> str:
    """A value as the file wrote it: strings quoted TOML-style, numbers exactly (repr)."""
    if isinstance(value, str):
        text = value if len(value) <= 100 else value[:60] + f"... ({len(value)} characters)"
        return '"' + _escaped(text.replace("\\", "\\\\").replace('"', '\\"')) + '"'
    if isinstance(value, (list, tuple)):
        items = [shown(v) for v in value[:MAX_SHOWN_ITEMS]]
        more = f", ... ({len(value)} items)" if len(value) > MAX_SHOWN_ITEMS else ""
        return "[" + ", ".join(items) + more + "]"
    if isinstance(value, dict):
        items = [f"{_escaped(str(k))} = {shown(v)}" for k, v in list(value.items())[:MAX_SHOWN_ITEMS]]
        more = f", ... ({len(value)} keys)" if len(value) > MAX_SHOWN_ITEMS else ""
        return "{" + ", ".join(items) + more + "}"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int) and abs(value) >= 10**30:
        # repr of an integer beyond 4,300 digits raises; a message needs its size only
        return f"an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits"
    text = repr(value)
    return text if len(text) <= 100 else text[:60] + f"... ({len(text)} characters)"


# --------------------------------------------------------------------------------------------
# The public validation protocol
# --------------------------------------------------------------------------------------------


class SceneChecks:
    """What an effect's `check` receives: where the scene comes from, and how to refuse it.

    * ``source``: the file (or ``"<dict>"``) being validated, for messages;
    * ``fail(key, value, allowed, why="")``: the `SceneError` for a key whose value breaks a
      rule, worded like every other ("<file>: key 'section.key' = <value> is invalid: [why; ]
      allowed ...");
    * ``refuse(message)``: a `SceneError` for anything else, prefixed with the file.

    Raise what they return. A key set by an override (`load_scene(..., key=value)`,
    ``--set``) is reported as ``<file> (overridden)``.
    """

    def __init__(self, source: str, overridden: frozenset[str] | set[str] = frozenset()):
        self.source = source
        self.overridden = frozenset(overridden)

    def where(self, key: str) -> str:
        return f"{self.source} (overridden)" if key in self.overridden else self.source

    def fail(self, key: str, value: Any, allowed: str, why: str = "") -> SceneError:
        # a quoted number is a string in TOML: `mass = "1.0"` must not read as the number 1.0
        if isinstance(value, str) and _looks_numeric(value):
            allowed += " (a quoted value is a string in TOML: write the number without quotes)"
        because = f"{why}; " if why else ""
        return SceneError(f"{self.where(key)}: key '{key}' = {shown(value)} is invalid: {because}allowed {allowed}")

    def refuse(self, message: str, key: str | None = None) -> SceneError:
        return SceneError(f"{self.where(key) if key else self.source}: {message}")


# --------------------------------------------------------------------------------------------
# Validation of a whole scene
# --------------------------------------------------------------------------------------------

_SKIP = object()  # an effect-only key of an effect not listed: absent from the validated dict


class Validator(SceneChecks):
    """Validates one scene mapping against an effect registry (name -> `Effect`).

    ``unusable`` maps effect names a scene may not list to the reason (a plugin that failed
    to load, an effect the physics paths cannot honour); they are refused with it.
    """

    def __init__(self, source: str, overridden: set[str], registry: Mapping, unusable: Mapping[str, str] | None = None):
        super().__init__(source, overridden)
        self.registry = registry
        self.unusable = dict(unusable or {})
        self.schema = full_schema(registry)
        self.ranges = plausible_ranges(registry)
        self.owners = key_owners(registry)

    def validate(self, data: Mapping) -> tuple[dict, tuple[str, ...]]:
        """(validated dict with defaults filled in, effects in canonical order)."""
        if not isinstance(data, Mapping):
            raise self.refuse(f"a scene is a table of keys, not {type(data).__name__}")
        if nesting_depth(data) > MAX_DEPTH:
            deep = too_deep(data)
            raise self.refuse(f"key {shown_key(deep)} is {NESTED_TOO_DEEPLY}" if deep else NESTED_TOO_DEEPLY, deep)
        effects = self.effects(data.get("effects"))
        for key in data:
            if key not in self.schema:
                raise self.refuse(f"unknown key {shown_key(key)}{suggest(str(key), self.schema)}; "
                                  f"allowed top-level keys: {', '.join(self.schema)}")
        out: dict[str, Any] = {}
        for key, spec in self.schema.items():
            if isinstance(spec, dict):
                section = data.get(key, {})
                if not isinstance(section, dict):
                    raise self.fail(key, section, "a table of keys")
                out[key] = self.section(key, section, spec, effects)
            else:
                value = self.entry(key, data.get(key), spec, effects)
                if value is not _SKIP:
                    out[key] = value
        out["effects"] = list(effects)
        self.cross_checks(out)
        # each effect's own rules (listed or not: `self.name in effects` tells)
        for effect in self.registry.values():
            effect.check(self, out, effects)
        return out, effects

    def effects(self, value: Any) -> tuple[str, ...]:
        known = ", ".join(self.registry)
        if value is None:
            raise self.refuse(f"missing key 'effects' (allowed: a list of {known})")
        if not isinstance(value, (list, tuple)) or not all(isinstance(e, str) for e in value):
            raise self.fail("effects", value, f"a list of effect names from {known}")
        for e in value:
            if e in self.unusable:
                raise self.refuse(f"key 'effects' lists {e!r}, which cannot be used: {self.unusable[e]}", "effects")
            if e not in self.registry:
                raise self.refuse(f"key 'effects' has unknown effect {e!r}{suggest(e, self.registry)}; "
                                  f"allowed: {known}", "effects")
        if len(set(value)) != len(value):
            raise self.fail("effects", value, "each effect listed once")
        for e in value:
            for need in self.registry[e].needs:
                if need not in value:
                    raise self.refuse(f"key 'effects': effect {e!r} needs effect {need!r} in the list", "effects")
        for name, effect in self.registry.items():
            if effect.required and name not in value:
                raise self.refuse(f"key 'effects' must include {name!r} (a string needs it)", "effects")
        return tuple(e for e in self.registry if e in value)  # canonical order: the registry's

    def section(self, name: str, section: dict, spec: dict[str, Key], effects) -> dict:
        for key in section:
            if key not in spec:
                raise self.refuse(f"unknown key {shown_key(f'{name}.{key}')}{suggest(str(key), spec)}; "
                                  f"allowed in [{name}]: {', '.join(spec)}")
        out = {}
        for key, s in spec.items():
            value = self.entry(f"{name}.{key}", section.get(key), s, effects)
            if value is not _SKIP:
                out[key] = value
        return out

    def entry(self, key: str, given: Any, spec: Key, effects) -> Any:
        """One key's validated value; refused when it belongs to an effect not listed."""
        owner = self.owners.get(key)
        if spec.only_with_effect:
            needs = spec.required_by or ((owner,) if owner else ())
            if not all(e in effects for e in needs):
                if given is not None:
                    raise self.refuse(
                        f"key '{key}' = {shown(given)} is only allowed with effect "
                        f"{', '.join(repr(e) for e in needs)} in the list 'effects': "
                        f"add it there, or remove the key", key)
                return _SKIP
        value = self.value(key, given, spec, effects)
        if (owner is not None and owner not in effects and given is not None and not spec.kept_without_effect
                and value != _plain(spec.default)):
            keep = f" (without it the key keeps its default, {shown(_plain(spec.default))})" \
                if spec.default is not None else ""
            raise self.refuse(f"key '{key}' = {shown(given)} is only used with effect '{owner}', which the list "
                              f"'effects' does not include: add '{owner}' to 'effects', or remove the key{keep}", key)
        return value

    def value(self, key: str, given: Any, spec: Key, effects) -> Any:
        out = self._value(key, given, spec, effects)
        if key in self.ranges and given is not None:
            self.plausible(key, given, out)
        return out

    def plausible(self, key: str, raw: Any, value: Any) -> None:
        lo, hi = self.ranges[key]
        # a vector's length from the numbers as given (a nonzero rule has normalised `value`)
        mag = vector_length(_flat_numbers(raw)) if isinstance(raw, (list, tuple)) else abs(float(value))
        if mag != 0.0 and not lo <= mag <= hi:
            size = " (its length is beyond the largest float64, 1.8e308)" if math.isinf(mag) else ""
            raise SceneError(
                f"{self.where(key)}: key '{key}' = {shown(raw)} is implausible{size}: allowed a magnitude in "
                f"[{lo:g}, {hi:g}] (SI units; see models/README.md). Check the units and the exponent")

    def _value(self, key: str, value: Any, spec: Key, effects) -> Any:
        if value is None:
            needed = spec.required or (spec.required_by is not None and all(e in effects for e in spec.required_by))
            if needed:
                why = f" (needed by effect {', '.join(spec.required_by)})" if spec.required_by else ""
                allowed = "a string" if spec.kind == "str" else RULE_TEXT.get(spec.rule, spec.kind)
                raise self.refuse(f"missing key '{key}'{why}: allowed {allowed}")
            return _plain(spec.default)
        if (spec.required_by is not None and not all(e in effects for e in spec.required_by)
                and _is_default(value, spec.default)):
            # the default of a key whose effect is not listed, as `Scene.to_dict` writes it back
            # for a file without that key: `with_` must accept the scene it was given (a reel
            # key's default, e.g. guide_length = 0, need not meet the rule it has with a reel)
            return _plain(spec.default)
        if spec.kind == "str":
            return self.text(key, value, spec.rule)
        if spec.kind == "effects":
            return list(value)
        if spec.kind == "float":
            v = self.number(key, value, spec.rule)
            if spec.rule == "stretch" and not STRETCH_RANGE[0] <= v <= STRETCH_RANGE[1]:
                raise self.fail(key, value, RULE_TEXT["stretch"])
            return v
        if spec.kind == "int":
            return self.number(key, value, spec.rule, integer=True)
        if spec.kind == "vec3":
            return list(self.vector(key, value, spec.rule))
        if spec.kind == "mat3":
            return [list(r) for r in self.matrix(key, value, spec.rule)]
        raise AssertionError(spec.kind)

    # -- scalars, strings, vectors, matrices ---------------------------------------------
    def text(self, key: str, value: Any, rule: str) -> str:
        if rule == "mass_model" and not (isinstance(value, str) and value in MASS_MODELS):
            raise self.fail(key, value, RULE_TEXT["mass_model"])
        if not isinstance(value, str):
            raise self.fail(key, value, "a string")
        if rule == "name" and not is_safe_name(value):
            raise self.fail(key, value, f"a name of {NAME_RULE}")
        if rule == "line" and (len(value) > MAX_DESCRIPTION
                               or any(unicodedata.category(c) in _UNPRINTABLE for c in value)):
            raise self.fail(key, value, RULE_TEXT["line"])
        return value

    def number(self, key: str, value: Any, rule: str, integer: bool = False) -> float | int:
        allowed = RULE_TEXT.get(rule, "a finite number")
        if not _finite_number(value):
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
        allowed = {"positive": "3 finite numbers > 0", "nonzero": RULE_TEXT["nonzero"]}.get(rule, "3 finite numbers")
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise self.fail(key, value, allowed)
        out = []
        for x in value:
            if not _finite_number(x):
                raise self.fail(key, value, allowed)
            out.append(float(x))
        if rule == "positive" and not all(x > 0 for x in out):
            raise self.fail(key, value, allowed)
        if rule == "nonzero":
            out = self.direction(key, value, out, allowed)
        return tuple(out)

    def direction(self, key: str, value: Any, numbers: list[float], allowed: str) -> list[float]:
        """``numbers`` divided by their length, which must lie in `DIRECTION_LENGTH`. The length is
        taken without squaring (`vector_length`): summed squares overflow past 1.3e154 and made
        [1e200, 0, 1e200] the "unit" vector (0, 0, 0); an overflowing length has its own message."""
        n = vector_length(numbers)
        lo, hi = DIRECTION_LENGTH
        if math.isinf(n):
            raise self.fail(key, value, allowed, "its length overflows a float64 (it is beyond 1.8e308), so it "
                                                 "cannot be normalised")
        if n == 0.0:
            raise self.fail(key, value, allowed, "a zero vector has no direction")
        if not lo <= n <= hi:
            raise self.fail(key, value, allowed, f"its length {n:.3g} is outside [{lo:g}, {hi:g}]")
        # inside the range the squares are normal numbers: normalised as always (bit for bit,
        # so that the shipped scenes keep their `Scene.key()`)
        n = math.sqrt(sum(x * x for x in numbers))
        unit = [x / n for x in numbers]
        if not abs(vector_length(unit) - 1.0) <= 1e-12:  # never store a vector that is not a direction
            raise self.fail(key, value, allowed, "it does not normalise to a unit vector")
        return unit

    def matrix(self, key: str, value: Any, rule: str) -> tuple:
        allowed = RULE_TEXT[rule]
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise self.fail(key, value, allowed)
        if not all(isinstance(row, (list, tuple)) and len(row) == 3 for row in value):
            raise self.fail(key, value, allowed)
        if not all(_finite_number(x) for row in value for x in row):
            raise self.fail(key, value, allowed + ", of finite numbers")
        m = np.array(value, dtype=float)
        if rule == "rotation":
            # a rotation's entries are direction cosines: bounding them first keeps m^T m finite
            # (entries near 1e200 overflowed it)
            if np.abs(m).max() > 1.0 + 1e-9:
                raise self.fail(key, value, allowed, "an entry lies outside [-1, 1], where a rotation's entries are")
            if np.abs(m.T @ m - np.eye(3)).max() > 1e-9 or abs(np.linalg.det(m) - 1.0) > 1e-9:
                raise self.fail(key, value, allowed)
        if rule == "spd":
            # judged on m / max|m| (definiteness does not change with a positive factor), so that
            # entries near 1e308 do not overflow m - m^T; asymmetry up to 1e-12 max(1, max|m|)
            scale = float(np.abs(m).max())
            if scale == 0:
                raise self.fail(key, value, allowed)
            unit = m / scale
            asymmetry = np.abs(unit - unit.T).max() if scale >= 1 else np.abs(m - m.T).max()
            if asymmetry > 1e-12 or np.linalg.eigvalsh(unit).min() <= 0:
                raise self.fail(key, value, allowed)
        return tuple(tuple(float(x) for x in row) for row in value)

    # -- rules across keys -------------------------------------------------------------------
    def cross_checks(self, d: dict) -> None:
        """The structural rules between keys: guide way, deployed length, element length."""
        s, r, i = d["string"], d["reel"], d["initial"]
        L, guide, N, ell = s["total_length"], r["guide_length"], s["elements"], i["deployed_length"]
        if not guide < L:
            raise self.fail("reel.guide_length", guide, f"0 <= guide_length < string.total_length = {L!r} "
                                                        f"(the guide way is part of the string)")
        if not ell < L - guide:
            raise self.fail("initial.deployed_length", ell,
                            f"0 < deployed_length < total_length - guide_length = {L - guide!r}")
        if not ell >= N * MIN_ELEMENT_LENGTH:
            raise self.fail("initial.deployed_length", ell,
                            f"deployed_length >= string.elements x {MIN_ELEMENT_LENGTH:g} m "
                            f"= {N * MIN_ELEMENT_LENGTH:g} m "
                            f"(every element at least {MIN_ELEMENT_LENGTH * 1e3:g} mm long at the start: a shorter "
                            f"one has an axial period l sqrt(mu/EA) too short to integrate)")
        if not r["min_deployed_length"] < ell:
            raise self.fail("reel.min_deployed_length", r["min_deployed_length"],
                            f"0 <= min_deployed_length < initial.deployed_length = {ell!r}")


def shown_key(key: Any) -> str:
    return f"'{_escaped(key)}'" if isinstance(key, str) else shown(key)
