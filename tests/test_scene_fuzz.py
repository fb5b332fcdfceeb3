"""Every scene input ends in a `SceneError` or a scene: a property-based fuzzer (hypothesis).

Scenes are generated from the schema's own key table (`models.scene.schema()`: the structural
keys plus every registered effect's, so a key an effect adds is fuzzed with no edit here), each
key given either a value of its kind near the plausible range (`plausible_ranges()`) or a
hostile one: huge, tiny, NaN, infinite, huge integers, wrong types, nested lists, wrong
lengths, tables, and, where Python objects can go, None, complex, Decimal, numpy arrays.
Keys are dropped, unknown keys added, sections replaced and effects toggled. Each scene is fed
to `load_scene` in one of five ways: as a TOML file, as raw bytes (the file's text cut short,
with junk, a flipped byte, a BOM, or not UTF-8), as overrides of a shipped scene (its name or
its loaded `Scene`), as a mapping (`scene_from_dict`), and as the scene argument itself. The
property:

* the only exception is `SceneError`, its message one line; a RuntimeWarning (an overflow in
  numpy) during validation is an error too;
* an accepted scene builds a model whose initial energy and energy scale are finite.

The default run is bounded (a fixed seed, `DEFAULT_EXAMPLES`, seconds); ``-m slow`` runs
`SLOW_EXAMPLES` (``REELBENCH_FUZZ_EXAMPLES`` and ``REELBENCH_FUZZ_SEED`` change both).
The same hostile values go through ``--set`` of ``simulate`` and ``run``: one ``error:``
line and exit 2 where the scene refuses them, never a traceback.
"""

import copy
import math
import os
import subprocess
import sys
import time
import warnings
from collections import Counter
from decimal import Decimal
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from _toml import to_toml, toml_value
from reelbench.models import SceneError, available_scenes, build_model, load_scene, scene_from_dict
from reelbench.models.schema import MASS_MODELS, NAME_PATTERN
from reelbench.models.scene import EFFECTS, plausible_ranges, schema

DEFAULT_EXAMPLES = 250
SLOW_EXAMPLES = int(os.environ.get("REELBENCH_FUZZ_EXAMPLES", "5000"))
FUZZ_SEED = int(os.environ.get("REELBENCH_FUZZ_SEED", "31"))
HANG_GUARD_S = 10.0
#: element counts of the generated valid scenes: few, so that the model's JAX operations are
#: compiled for few shapes (each new one costs seconds); the hostile integers reach the others
ELEMENTS = (1, 2, 3)


def _keys(table) -> dict:
    """{dotted key: Key} of the schema's table (top-level keys without a dot)."""
    out = {}
    for name, spec in table.items():
        if isinstance(spec, dict):
            out.update({f"{name}.{key}": s for key, s in spec.items()})
        else:
            out[name] = spec
    return out


SCHEMA = schema()
KEYS = _keys(SCHEMA)
SECTIONS = [name for name, spec in SCHEMA.items() if isinstance(spec, dict)]
RANGES = plausible_ranges()
#: the shipped scenes, and as validated mappings with few elements (see `ELEMENTS`)
SHIPPED = {name: load_scene(name) for name in available_scenes()}
BASES = {}
for _name in available_scenes():
    _d = SHIPPED[_name].to_dict()
    _d["string"]["elements"] = min(_d["string"]["elements"], ELEMENTS[-1])
    BASES[_name] = _d
#: an override's bare name where it is unambiguous (`load_scene(name, elements=3)`)
BARE = {k.split(".")[-1]: k for k in KEYS if sum(d.split(".")[-1] == k.split(".")[-1] for d in KEYS) == 1}

# ------------------------------------------------------------------------------------------
# Values
# ------------------------------------------------------------------------------------------
EDGE_NUMBERS = [1e308, -1e308, sys.float_info.max, -sys.float_info.max, 1e200, -1e200, 1.4e154, 1e155, 1e-155,
                1e-200, 1e-300, 5e-324, -5e-324, 0.0, -0.0, 1.0, -1.0]
NON_FINITE = [math.nan, math.inf, -math.inf]
BIG_INTEGERS = [2**53, 2**53 + 1, 2**63 - 1, -(2**63), 10**20, 10**400, 10**5000, 0, -1, 10_000, 10_001]

edge_numbers = st.sampled_from(EDGE_NUMBERS + NON_FINITE)
hostile_numbers = st.one_of(edge_numbers, st.sampled_from(BIG_INTEGERS), st.floats(),
                            st.integers(min_value=10_001), st.integers(max_value=0))
#: strings TOML can hold (no lone surrogates)
texts = st.one_of(st.text(st.characters(blacklist_categories=("Cs",)), max_size=8),
                  st.sampled_from(["", " ", "1.0", "nan", "inf", "1e308", "0", "[1, 2, 3]", "consistent ",
                                   "a\nb", "x\u2028y", "\x00", "é" * 600, "../../etc/passwd"]))


def _log_uniform(lo, hi):
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: 10.0 ** e)


def plausible_numbers(key):
    """Magnitudes across the key's plausible range, at its ends and just outside."""
    lo, hi = RANGES.get(key, (1e-3, 1e3))
    low = lo if lo > 0 else min(1e-9, hi * 1e-12)
    ends = st.sampled_from([lo, hi, low * (1 - 1e-9), hi * (1 + 1e-9), hi * 10.0])
    return st.one_of(_log_uniform(low, hi), ends)


def rotations():
    def rotation(q):
        q = np.asarray(q)
        w, x, y, z = q / np.linalg.norm(q)
        return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]

    q = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
    return q.map(rotation)


def diagonal(j):
    return [[j[0], 0.0, 0.0], [0.0, j[1], 0.0], [0.0, 0.0, j[2]]]


def valid_values(key, spec):
    """Values of the key's kind, mostly within its rule and plausible range."""
    if spec.kind == "float":
        number = plausible_numbers(key)
        return number if spec.rule in ("positive", "nonnegative", "stretch") else st.one_of(number, number.map(
            lambda x: -x))
    if spec.kind == "int":
        return st.sampled_from(ELEMENTS)
    if spec.kind == "vec3":
        part = st.one_of(st.just(0.0), plausible_numbers(key), plausible_numbers(key).map(lambda x: -x))
        return st.lists(part, min_size=3, max_size=3)
    if spec.kind == "mat3" and spec.rule == "rotation":
        return rotations()
    if spec.kind == "mat3":
        moment = st.one_of(_log_uniform(1e-3, 1e3), _log_uniform(1e-320, 1e308))
        return st.lists(moment, min_size=3, max_size=3).map(diagonal)
    if spec.kind == "str" and spec.rule == "name":
        return st.from_regex(NAME_PATTERN, fullmatch=True)
    if spec.kind == "str" and spec.rule == "mass_model":
        return st.sampled_from(MASS_MODELS)
    if spec.kind == "str":
        return st.text(st.characters(whitelist_categories=("L", "N", "Zs")), max_size=20)
    if spec.kind == "effects":
        return st.lists(st.sampled_from(list(EFFECTS)), unique=True, max_size=len(EFFECTS))
    raise AssertionError(spec.kind)


def hostile_data():
    """Values TOML can hold that break some rule: numbers at the edges, wrong types and shapes."""
    numbers = st.one_of(hostile_numbers, st.floats(-1e3, 1e3))
    return st.one_of(
        hostile_numbers, texts, st.booleans(),
        st.lists(numbers, max_size=5),  # wrong lengths, and 3-vectors of edge numbers
        st.lists(edge_numbers, min_size=3, max_size=3),
        st.lists(st.lists(numbers, min_size=3, max_size=3), min_size=3, max_size=3),  # 3x3 of edge numbers
        st.lists(edge_numbers, min_size=3, max_size=3).map(diagonal),
        st.lists(st.lists(numbers, max_size=4), max_size=4),  # ragged: [[1.0, 2.0], [3.0]]
        rotations().map(lambda r: (np.array(r) * 1e200).tolist()),
        st.lists(st.one_of(texts, st.booleans()), min_size=1, max_size=3),
        st.just([[[[[1.0]]]]]),
        st.dictionaries(texts, numbers, max_size=2),
    )


def hostile_objects():
    """Values only Python can give (overrides, mappings)."""
    return st.sampled_from([
        None, complex(1, 2), Decimal("1.5"), Decimal("NaN"), Fraction(1, 3), b"1.0", bytearray(b"x"), {1, 2, 3},
        (0.0, 0.0, 1.0), np.float64(np.nan), np.float64(1e308), np.int64(3), np.array([0.0, 0.0, 1.0]),
        np.array([[1e200] * 3] * 3), np.zeros((3, 3, 3)), object(), "\ud800", range(3), [None, None, None],
        [np.nan] * 3, [Decimal(1)] * 3, float, Path("x"),
    ])


def values_for(key, python):
    spec = KEYS.get(key)
    hostile = st.one_of(hostile_data(), hostile_objects()) if python else hostile_data()
    if spec is None:  # an unknown key
        return hostile
    return st.one_of(valid_values(key, spec), valid_values(key, spec), hostile)


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------
DROP = object()


@st.composite
def edits(draw, base, mode):
    """[(path, value)]: changes to ``base``, a path being (key,) or (section, key); DROP removes.
    Python objects as values in overrides and mappings, and keys that are not strings in a mapping."""
    python = mode in ("override", "mapping")
    out = []
    for _ in range(draw(st.integers(0, 6))):
        what = draw(st.sampled_from(["key", "key", "key", "key", "drop", "unknown", "section", "effects"]))
        if what in ("key", "drop"):
            key = draw(st.sampled_from(sorted(KEYS)))
            value = DROP if what == "drop" else draw(values_for(key, python))
            out.append((tuple(key.split(".")), value))
        elif what == "unknown":
            name = draw(st.one_of(texts, st.sampled_from(sorted(KEYS)).map(lambda k: k.split(".")[-1] + "s"),
                                  *([st.integers(), st.none(), st.just((1, 2))] if mode == "mapping" else [])))
            where = draw(st.sampled_from([None, *SECTIONS]))
            out.append(((name,) if where is None else (where, name), draw(values_for(None, python))))
        elif what == "section":
            out.append(((draw(st.sampled_from(SECTIONS)),), draw(values_for(None, python))))
        else:  # one effect more or less: its keys become required or refused
            listed = list(base["effects"])
            toggled = draw(st.sampled_from(list(EFFECTS)))
            listed = [e for e in listed if e != toggled] if toggled in listed else listed + [toggled]
            out.append((("effects",), listed))
    return out


def apply_edits(data, changes):
    d = copy.deepcopy(data)
    for path, value in changes:
        table = d
        if len(path) == 2:
            table = d.setdefault(path[0], {})
            if not isinstance(table, dict):
                continue  # the section was replaced by a value: the key has nowhere to go
        if value is DROP:
            table.pop(path[-1], None)
        else:
            table[path[-1]] = value
    return d


def overrides_of(changes, elements, bare):
    """The changes as `load_scene` keywords: dotted names, or bare ones where ``bare`` says so
    and the name is unambiguous; DROP as None (the default)."""
    out = {"string.elements": elements}
    for (path, value), short in zip(changes, bare):
        dotted = ".".join(path)
        name = path[-1] if short and BARE.get(path[-1]) == dotted else dotted
        out[name] = None if value is DROP else value
    return out


def mutated(raw, draw):
    edit = draw(st.sampled_from(["cut", "junk", "flip", "bom", "latin1", "binary", "none"]))
    if edit == "cut":
        return raw[: draw(st.integers(0, len(raw)))]
    if edit == "junk":
        at = draw(st.integers(0, len(raw)))
        return raw[:at] + draw(st.binary(min_size=1, max_size=16)) + raw[at:]
    if edit == "flip":
        at = draw(st.integers(0, len(raw) - 1))
        return raw[:at] + bytes([raw[at] ^ (1 << draw(st.integers(0, 7)))]) + raw[at + 1:]
    if edit == "bom":
        return b"\xef\xbb\xbf" + raw
    if edit == "latin1":
        return raw.replace(b"=", "= \u00e9".encode("latin-1"), 1)
    if edit == "binary":
        return draw(st.binary(max_size=64))
    return raw


@st.composite
def cases(draw):
    """(mode, what to load): a generated scene in one of the five forms `load_scene` takes."""
    mode = draw(st.sampled_from(["file", "file", "bytes", "override", "override", "mapping", "argument"]))
    name = draw(st.sampled_from(sorted(BASES)))
    base = BASES[name]
    changes = draw(edits(base, mode))
    if mode == "override":
        bare = draw(st.lists(st.booleans(), min_size=len(changes), max_size=len(changes)))
        # of the shipped file, or of its loaded `Scene` (`Scene.with_`, which starts from `to_dict`)
        start = draw(st.sampled_from([name, SHIPPED[name]]))
        return mode, (start, overrides_of(changes, base["string"]["elements"], bare))
    if mode == "argument":
        return mode, draw(st.one_of(texts, st.binary(max_size=16), st.integers(), st.none(),
                                    st.sampled_from([Path("/dev/null"), Path("."), "nosuch.toml", name + ".toml"])))
    data = apply_edits(base, changes)
    if mode == "mapping":
        return mode, data
    raw = to_toml(data).encode()
    return mode, (mutated(raw, draw) if mode == "bytes" else raw)


# ------------------------------------------------------------------------------------------
# The property
# ------------------------------------------------------------------------------------------
def load(mode, what, workdir: Path):
    if mode in ("file", "bytes"):
        path = workdir / "fuzzed.toml"
        path.write_bytes(what)
        return load_scene(path)
    if mode == "override":
        name, overrides = what
        return load_scene(name, **overrides)
    if mode == "mapping":
        return scene_from_dict(what, source="fuzzed.toml")
    return load_scene(what)


def assert_builds_a_finite_model(scene):
    from reelbench.models._jax import jnp

    model = build_model(scene)
    x, R, w = model.initial_state()
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(R)) and np.all(np.isfinite(w)), scene
    energy = float(model.energy(jnp.asarray(x), jnp.asarray(R), jnp.asarray(w)))
    assert math.isfinite(energy), (scene, energy)
    assert math.isfinite(model.energy_scale()), scene


def outcome(mode, what, workdir) -> str:
    """"refused" or "accepted"; anything else escaping `load_scene` fails the property."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # an overflow in numpy is not a validation
        try:
            scene = load(mode, what, workdir)
        except SceneError as exc:
            assert "\n" not in str(exc), str(exc)
            scene = None
    spent = time.perf_counter() - t0
    assert spent < HANG_GUARD_S, f"load_scene took {spent:.1f} s"
    if scene is None:
        return "refused"
    assert_builds_a_finite_model(scene)
    return "accepted"


def fuzz(workdir: Path, examples: int, fixed_seed: int | None) -> Counter:
    """Run the property over ``examples`` generated inputs; {(mode, outcome): count}."""
    counts: Counter = Counter()

    @settings(max_examples=examples, deadline=None, database=None, derandomize=fixed_seed is None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])
    @given(case=cases())
    def property(case):
        mode, what = case
        counts[mode, outcome(mode, what, workdir)] += 1

    if fixed_seed is not None:
        property = seed(fixed_seed)(property)
    property()
    return counts


def test_every_generated_scene_input_is_refused_with_a_scene_error_or_builds_a_finite_model(tmp_path):
    counts = fuzz(tmp_path, DEFAULT_EXAMPLES, None)
    print(dict(counts))
    # the property proves something only where both branches are reached
    for mode in ("file", "bytes", "override", "mapping", "argument"):
        assert counts[mode, "refused"] > 0, counts
    for mode in ("file", "override", "mapping"):
        assert counts[mode, "accepted"] > 0, counts


@pytest.mark.slow
def test_many_generated_scene_inputs_are_refused_with_a_scene_error_or_build_a_finite_model(tmp_path):
    t0 = time.perf_counter()
    counts = fuzz(tmp_path, SLOW_EXAMPLES, FUZZ_SEED)
    print(f"{sum(counts.values())} examples in {time.perf_counter() - t0:.0f} s: {dict(sorted(counts.items()))}")
    assert sum(n for (_, result), n in counts.items() if result == "accepted") > 0, counts


def test_the_schema_keys_are_all_fuzzed():
    """Generated from the key table: a key an effect adds is in it with no edit here."""
    for name, effect in EFFECTS.items():
        for section, keys in effect.keys.items():
            for key in keys:
                assert (f"{section}.{key}" if section else key) in KEYS, (name, key)
    assert {"string.elements", "initial.direction", "reel.exit_direction", "initial.attitude"} <= set(KEYS)


@pytest.mark.parametrize("overrides, fragments", [
    ({"initial.tip_velocity": [-1e308, 0, 0]}, ["'initial.tip_velocity'", "implausible", "[0, 10000]"]),
    ({"initial.tip_velocity": [1.7e308, 1.7e308, 0]}, ["'initial.tip_velocity'", "beyond the largest float64"]),
    ({"effects": [[1.0, 2.0], [3.0]]}, ["'effects'", "a list of effect names"]),
    ({"initial.attitude": [[1e200, 0, 0], [0, 1, 0], [0, 0, 1]]}, ["'initial.attitude'", "outside [-1, 1]",
                                                                    "rotation matrix"]),
    ({"initial.attitude": [[1e200, 1e200, 1e200]] * 3}, ["'initial.attitude'", "outside [-1, 1]"]),
    ({"body.inertia": [[1e308, 0, 0], [0, 1e308, 0], [0, 0, 1e308]]},
     ["'body.inertia'", "radius of gyration"]),
    ({"body.inertia": [[1e308, -1e308, 0], [-1e308, 1e308, 0], [0, 0, 1]]},
     ["'body.inertia'", "positive-definite"]),
    ({"body.inertia": [[5e-324, 0, 0], [0, 5e-324, 0], [0, 0, 5e-324]]}, ["'body.inertia'", "radius of gyration"]),
    ({"body.box": [1e300, 1e300, 1e300]}, ["'body.box'", "implausible"]),
    ({"reel.exit_direction": [-1.7e308, 1.7e308, 0]}, ["'reel.exit_direction'", "its length overflows a float64",
                                                       "length is in [1e-150, 1e+150]"]),
    ({"reel.exit_direction": [1e200, 0, 1e200]}, ["'reel.exit_direction'", "its length 1.41e+200 is outside"]),
    ({"initial.direction": [0, 0, 0]}, ["'initial.direction'", "a zero vector has no direction"]),
    ({"reel.center": np.zeros(3)}, ["'reel.center'", "3 finite numbers"]),
    ({"string.mass_model": np.array(["lumped", "x"])}, ["'string.mass_model'", "one of"]),
    ({"body.mass": 10**5000}, ["'body.mass'", "an integer of about 5001 digits"]),
    ({"description": "one\nline"}, ["'description'", "\\u000a", "line breaks"]),
    ({"description": "\ud800"}, ["'description'", "\\ud800"]),
    ({"initial.direction": [[[[1.0]]]]}, ["'initial.direction'", "nested too deeply"]),
])
def test_values_that_overflowed_or_raised_are_refused_naming_the_key_and_the_range(overrides, fragments):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(SceneError) as exc:
            load_scene("retrieval", **overrides)
    msg = str(exc.value)
    assert all(f in msg for f in fragments), msg
    assert "\n" not in msg and "[0.0, 0.0, 0.0]" not in msg
    msg.encode("utf-8")  # printable anywhere


def test_an_overflowing_direction_is_never_stored_and_a_large_one_still_normalises():
    """An overflowed exit direction was once stored as (0, 0, 0): now it is refused with its own
    message, and a direction whose squares alone would overflow still normalises."""
    with pytest.raises(SceneError, match="its length overflows a float64"):
        load_scene("deployment", exit_direction=[1.7e308, -1.7e308, 1e308])
    with pytest.raises(SceneError, match=r"its length 1.73e\+308 is outside"):
        load_scene("deployment", exit_direction=[1e308, 1e308, 1e308])
    assert load_scene("deployment", exit_direction=[0.0, 1e150, 0.0]).reel.exit_direction == (0.0, 1.0, 0.0)
    with pytest.raises(SceneError, match="is outside"):
        load_scene("deployment", exit_direction=[0.0, 1.2e150, 0.0])


def test_a_file_with_an_integer_too_long_to_read_is_refused(tmp_path):
    path = tmp_path / "long.toml"
    text = Path(SHIPPED["retrieval"].source).read_text()
    path.write_text(text.replace("mass = ", "mass = " + "9" * 5000 + " #", 1))
    with pytest.raises(SceneError, match="more than .* digits"):
        load_scene(path)


# ------------------------------------------------------------------------------------------
# The same values through --set on the command line
# ------------------------------------------------------------------------------------------
@pytest.fixture
def stubbed(monkeypatch):
    """The pipelines replaced by a recorder: an accepted command line does no work."""
    from reelbench.benchmark.cli import simulate
    from reelbench.benchmark.studies import grid

    calls = []
    for module, name in ((grid, "run_sweep"), (simulate, "simulate")):
        monkeypatch.setattr(module, name, lambda *a, _n=name, **k: calls.append(_n) or 0)
    return calls


def set_texts():
    """(key, --set value text): a schema key and a hostile value as JSON, or as bare text."""
    import json

    def as_json(value):
        """JSON text (NaN, Infinity included: json.loads reads them, as --set does), integers of
        any size included (json.dumps refuses beyond 4,300 digits)."""
        if isinstance(value, int) and not isinstance(value, bool):
            return toml_value(value)
        if isinstance(value, list):
            return "[" + ", ".join(as_json(v) for v in value) + "]"
        if isinstance(value, dict):
            return "{" + ", ".join(f"{json.dumps(str(k))}: {as_json(v)}" for k, v in value.items()) + "}"
        return json.dumps(value)

    key = st.sampled_from(sorted(KEYS))
    return key.flatmap(lambda k: st.tuples(st.just(k), st.one_of(
        values_for(k, python=False).filter(lambda v: not isinstance(v, str)).map(as_json),
        texts.filter(lambda t: "\x00" not in t),
        st.sampled_from(["[" * 5000 + "]" * 5000, "1" * 5000, "[-1e308,0,0]", "[[1e200,0,0],[0,1,0],[0,0,1]]",
                         "[[1.0,2.0],[3.0]]", "1e400", "-Infinity", "{\"a\": 1}", "null"]))))


def commands(key_text, out: Path):
    setting = f"{key_text[0]}={key_text[1]}"
    return [["simulate", "retrieval", "--integrators", "lgvi", "--dt", "0.01", "--set", setting,
             "--out", str(out / "o" / "t.npz")],
            ["run", "--scenes", "retrieval", "--integrators", "lgvi", "--set", setting, "--out", str(out / "o")]]


@settings(max_examples=60, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much,
                                 HealthCheck.function_scoped_fixture])
@given(key_text=set_texts())
def test_hostile_set_values_on_simulate_and_run_are_one_error_line_and_exit_2(tmp_path, capsys, stubbed, key_text):
    from reelbench.benchmark.cli.common import overrides as _overrides
    from reelbench.benchmark.cli.main import main
    from reelbench.benchmark.core.options import UsageError

    try:
        load_scene("retrieval", **_overrides([f"{key_text[0]}={key_text[1]}"]))
        refused = False
    except (SceneError, UsageError):
        refused = True
    for args in commands(key_text, tmp_path):
        stubbed.clear()
        rc = main(args)  # an exception escaping main fails the property
        err = capsys.readouterr().err
        assert "Traceback" not in err
        errors = [line for line in err.splitlines() if line.startswith("error:")]
        if refused:
            assert rc == 2 and not stubbed, (args, rc, err)
            assert len(errors) == 1 and err.strip() == errors[0], (args, err)
            assert key_text[0].split(".")[-1] in errors[0], (args, err)
        else:  # accepted by the scene: the pipeline is reached, or one error line (e.g. the size)
            assert (rc == 0 and stubbed) or (rc == 2 and len(errors) == 1), (args, rc, err)
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("setting", ["initial.tip_velocity=[-1e308,0,0]",
                                     "initial.attitude=[[1e200,0,0],[0,1,0],[0,0,1]]",
                                     "effects=[[1.0,2.0],[3.0]]", "direction=" + "[" * 3000 + "]" * 3000])
def test_the_reported_command_lines_end_in_one_error_line_and_exit_2(tmp_path, setting):
    """The command lines of the report, in a real process: exit 2 and one line, no traceback."""
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("REELBENCH_DEBUG", None)
    proc = subprocess.run([sys.executable, "-m", "benchmark", "simulate", "retrieval", "--integrators", "lgvi",
                           "--dt", "0.01", "--set", setting, "--out", str(tmp_path / "t.npz")],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in proc.stderr, proc.stderr
    assert setting.split("=")[0].split(".")[-1] in lines[0], lines[0]
