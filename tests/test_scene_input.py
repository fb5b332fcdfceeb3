"""Scene input that cannot hurt: names that are data, values that are checked through their
arithmetic, and files that are read only when they are small regular files.

Each case below was accepted (or crashed, hung, or read forever) before the schema refused it;
each is now a `SceneError` naming the file, the key and the rule, before any computation.
"""

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from reelbench.benchmark.cli.main import main
from reelbench.models import (EFFECTS, SceneError, available_scenes, load_scene, register_effect, scene_from_dict,
                    unregister_effect)
from reelbench.models import io as model_io
from reelbench.models.effects import Effect, Key
from reelbench.models.io import UnsafePath, inside
from reelbench.models.schema import MIN_ELEMENT_LENGTH
from reelbench.models.scene import MAX_SCENE_BYTES, SCENE_DIR

ROOT = Path(__file__).resolve().parent.parent

#: Every value of every shipped scene (all fields of the `Scene` but its file, and the
#: validated dict), hashed as the code before the schema module computed them.
SHIPPED = {
    "deployment": "bfcfab094ea2d93b", "deployment_to_end": "d876a946c9d508dd", "fast_spin": "925d691dbf998dd5",
    "fixed_length": "fa1733f4fd711dcf", "long_horizon": "44b78f625727340a", "many_elements": "0a0ec1ed46b08b5d",
    "near_slack": "434c0a2a6e439519", "reel_reversal": "c6edc11cd2cd083a", "retrieval": "389ce5bb81575649",
    "retrieval_to_limit": "c83b6b61137bb40b", "stiff_string": "b31f94537d6f16ec",
    # the fluid scenes (added with the buoyancy and drag effects)
    "deployment_in_water": "6efa15e901743d9d", "strong_drag": "d15c547f65ed3673", "towed": "0d82fba9eee8b1df",
    # a rigid body off its centre of mass in the current (added with body loads)
    "towed_offset": "4df61c1a42983eaa",
}


def _values_hash(scene) -> str:
    return hashlib.sha256((repr(dataclasses.replace(scene, source="")) + scene.raw).encode()).hexdigest()[:16]


def test_the_shipped_scenes_load_with_identical_values():
    assert {name: _values_hash(load_scene(name)) for name in available_scenes()} == SHIPPED


def scene_text(scene="fixed_length", /, **replace) -> str:
    """A shipped scene's text with whole lines replaced: ``replace`` maps a key to its new line."""
    lines = (SCENE_DIR / f"{scene}.toml").read_text().splitlines()
    out = []
    for line in lines:
        key = line.split("=")[0].strip()
        out.append(replace.pop(key) if key in replace else line)
    assert not replace, replace  # every replaced key exists in the file
    return "\n".join(out) + "\n"


def refused(path_or_data, *fragments, **overrides) -> str:
    with pytest.raises(SceneError) as err:
        if isinstance(path_or_data, dict):
            scene_from_dict(path_or_data, source="bad.toml", **overrides)
        else:
            load_scene(path_or_data, **overrides)
    msg = str(err.value)
    for frag in fragments:
        assert frag in msg, msg
    return msg


# ------------------------------------------------------------------------------------------
# Names are data, never paths
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["../../elsewhere/evil", "", "x" * 300, "a/b", "a\\b", ".hidden", "-rf", "a..b",
                                  "with space", "tab\t", "nul\x00", "é", "/abs"],
                         ids=lambda n: repr(n if len(n) < 20 else f"{n[:5]}...({len(n)})"))
def test_a_scene_name_that_is_not_a_plain_file_name_is_refused(tmp_path, name):
    path = tmp_path / "s.toml"
    path.write_text(scene_text(name=f"name = {json.dumps(name)}"))  # JSON's escapes are TOML's
    msg = refused(path, str(path), "key 'name'", "A-Z a-z 0-9 _ . -", "without '..'")
    assert len(msg) < 600  # a 300-character name is shortened in the message


@pytest.mark.parametrize("name", ["fixed_length", "a", "Run-2.b_3", "9" * 64])
def test_plain_names_are_accepted(name):
    assert load_scene("fixed_length", name=name).name == name


def test_a_name_is_checked_when_overridden_too():
    refused("fixed_length", "(overridden)", "key 'name'", name="../evil")


def test_simulate_and_run_refuse_a_traversing_name_before_writing_anything(tmp_path, monkeypatch, capsys):
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    (work / "evil.toml").write_text(scene_text(name='name = "../../elsewhere/evil"'))
    monkeypatch.chdir(work)
    assert main(["simulate", "evil.toml", "--set", "elements=1", "--t-end", "0.02", "--dt", "0.01"]) == 2
    assert main(["run", "--scenes", "evil.toml", "--integrators", "lgvi", "--quick", "--out", "out"]) == 2
    err = capsys.readouterr().err
    assert err.count("error: evil.toml: key 'name'") == 2, err
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == ["a", "a/b", "a/b/evil.toml"]


EVIL = "../../elsewhere/evil"
#: Every command that writes files, given a traversing name where it takes one ({s}: a scene
#: file named EVIL, {d}: a trajectory file); each must refuse it before writing anything.
TRAVERSALS = [
    ["simulate", "{s}", "--set", "elements=1", "--t-end", "0.02", "--dt", "0.01"],
    ["simulate", "fixed_length", "--integrators", EVIL, "--t-end", "0.02", "--dt", "0.01"],
    ["run", "--scenes", "{s}", "--integrators", "lgvi", "--quick", "--out", "out"],
    ["run", "--scenes", "fixed_length", "--integrators", EVIL, "--quick", "--out", "out"],
    ["figures", "{d}", "--scenes", "{s}"],
    ["speed", "--scenes", "{s}", "--elements", "2", "--out", "out/speed.md"],
    ["stability", "--scenes", EVIL, "--out", "out"],
    ["stability", "--integrators", EVIL, "--out", "out"],
    ["xval", "--scenes", "{s}", "--out", "out"],
    ["check", "--update", "--integrators", EVIL, "--baseline", "out/drift.csv"],
    ["reel-reversal", "--scenes", "{s}", "--cache-dir", "out"],
    ["reel-reversal", "--integrators", EVIL, "--cache-dir", "out"],
]


@pytest.mark.parametrize("args", TRAVERSALS, ids=lambda a: " ".join(a[:3]))
def test_every_command_that_writes_refuses_a_traversing_name_before_writing_anything(tmp_path, monkeypatch, capsys,
                                                                                      args):
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    (work / "evil.toml").write_text(scene_text(name=f'name = "{EVIL}"'))
    (work / "t.npz").write_bytes(b"")
    monkeypatch.chdir(work)
    assert main([a.format(s="evil.toml", d="t.npz") for a in args]) == 2
    err = capsys.readouterr().err
    assert "error: " in err and "Traceback" not in err, err
    assert "evil" in err.splitlines()[-1], err  # the message names what was refused
    made = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    assert made == ["a", "a/b", "a/b/evil.toml", "a/b/t.npz"], made  # not even an empty --out


def test_the_writers_themselves_keep_a_name_inside_their_directory(tmp_path):
    """Past the command line's checks: a name from a table read back (runs.csv) or from a scene
    object never validated is refused by the writer that would put it into a file name."""
    import pandas as pd

    from reelbench.benchmark.figures import plots
    from reelbench.benchmark.core.reference import reference_path
    from reelbench.benchmark.runs import table

    out = tmp_path / "out"
    out.mkdir()
    rows = pd.DataFrame([{"scene": EVIL, "integrator": "lgvi", "setting": "dt=0.01", "status": "ok"}])
    with pytest.raises(UnsafePath):
        plots.work_precision(rows, EVIL, out)
    scene = dataclasses.replace(load_scene("fixed_length"), name=EVIL)  # past the schema
    with pytest.raises(UnsafePath):
        reference_path(scene, 1.0, 0.02, out)
    row = {"scene": EVIL, "integrator": "lgvi", "setting": "dt=0.01", "status": "ok"}
    assert "not a plain name" in table.check_row(row)
    assert not list(tmp_path.parent.glob("elsewhere"))


def test_inside_joins_a_name_and_refuses_a_path_out_of_the_directory(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    assert inside(out, "fig.png") == out.resolve() / "fig.png"
    assert inside(out, "sub", "fig.png") == out.resolve() / "sub" / "fig.png"
    assert inside(str(out), "a..b.png").name == "a..b.png"
    for parts in (("../evil.png",), ("sub", "..", "..", "evil"), ("/etc/passwd",), ("",), (".",), ("a\x00b",), ()):
        with pytest.raises(UnsafePath):
            inside(out, *parts)
    # a link planted inside the directory that points out of it is followed, and refused
    (out / "link").symlink_to(tmp_path)
    with pytest.raises(UnsafePath, match="leads outside"):
        inside(out, "link", "evil.png")
    (out / "inner").mkdir()
    (out / "ok").symlink_to(out / "inner")
    assert inside(out, "ok", "f.png") == out.resolve() / "inner" / "f.png"


# ------------------------------------------------------------------------------------------
# Values checked through their arithmetic
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scene, key, line, shown", [
    ("fixed_length", "initial.direction", "direction = [1e200, 0, 1e200]", "[1e+200, 0, 1e+200]"),
    ("fixed_length", "initial.direction", "direction = [1e-200, 0.0, 0.0]", "[1e-200, 0.0, 0.0]"),
    ("deployment", "reel.exit_direction", "exit_direction = [1e200, 0, 1e200]", "[1e+200, 0, 1e+200]"),
    ("deployment", "reel.exit_direction", "exit_direction = [-1.7e308, 1.7e308, 0]", "[-1.7e+308, 1.7e+308, 0]"),
])
def test_a_direction_whose_length_is_not_representable_is_refused_as_written(tmp_path, scene, key, line, shown):
    """[1e200, 0, 1e200] normalised to (0, 0, 0): the deployment scene then ran with t_g = 0
    (work -18.03 J instead of -0.246 J at 8 s) and the fixed-length one hung in the reference."""
    path = tmp_path / "s.toml"
    path.write_text(scene_text(scene, **{line.split("=")[0].strip(): line}))
    msg = refused(path, f"key '{key}' = {shown} is invalid", "length is in [1e-150, 1e+150]")
    assert "[0.0, 0.0, 0.0]" not in msg


def test_a_large_but_representable_direction_is_normalised():
    assert load_scene("fixed_length", direction=[1e100, 0, 1e100]).initial.direction == pytest.approx(
        (2**-0.5, 0.0, 2**-0.5), rel=1e-15)


def test_the_deployed_length_has_a_physical_minimum():
    """1e-300 m validated, then the reference solve looped for minutes and the LGVI failed Newton at
    step 1. Each element must be at least MIN_ELEMENT_LENGTH long at the start."""
    for ell in (1e-300, 1e-6, 0.999 * 10 * MIN_ELEMENT_LENGTH):
        refused("fixed_length", "key 'initial.deployed_length'", "string.elements x 0.001 m = 0.01 m",
                deployed_length=ell)
    assert load_scene("fixed_length", deployed_length=10 * MIN_ELEMENT_LENGTH).initial.deployed_length == 0.01
    refused("fixed_length", "0.1 m", elements=100, deployed_length=0.05)


def test_the_guide_way_must_be_shorter_than_the_string():
    refused("deployment", "key 'reel.guide_length' = 40.0", "guide_length < string.total_length = 40.0",
            guide_length=40.0)


@pytest.mark.parametrize("value, fragments", [
    ([[1e300, 0, 0], [0, 1e300, 0], [0, 0, 1e300]], ["key 'body.inertia'", "implausible", "radius of gyration"]),
    ([[1e-30, 0, 0], [0, 1e-30, 0], [0, 0, 1e-30]], ["key 'body.inertia'", "implausible", "[1e-07, 10000] m"]),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 2.5]], ["key 'body.inertia'", "J1 <= J2 + J3", "1, 1, 2.5"]),
])
def test_an_absurd_or_impossible_inertia_is_refused(value, fragments):
    refused("fixed_length", *fragments, inertia=value)


def test_a_box_with_a_vanishing_edge_is_refused_by_its_inertia():
    refused("fixed_length", "key 'body.box'", "radius of gyration", box=[1.0, 1e-300, 1e-300])
    assert load_scene("fixed_length", inertia=[[1, 0, 0], [0, 2, 0], [0, 0, 2.5]]).body.inertia[2][2] == 2.5


def test_a_key_of_an_effect_not_listed_is_refused_naming_the_effect_to_add():
    """control_moment = 5 on a fixed-length scene was accepted and ignored."""
    refused("fixed_length", "(overridden): key 'reel.control_moment' = 5", "only used with effect 'reel_control'",
            "add 'reel_control' to 'effects'", control_moment=5)
    refused("fixed_length", "key 'string.axial_damping'", "effect 'axial_damping'", axial_damping=0.1)
    point = load_scene("fixed_length", effects=["gravity", "elasticity"], angular_velocity=[0, 0, 0])
    assert point.to_dict()["body"]["box"] is None  # the override of `effects` dropped the keys of rigid_body
    refused(point, "key 'body.box'", "add 'rigid_body'", box=[0.6, 0.4, 0.2])
    refused(point, "key 'initial.angular_velocity'", "only used with effect 'rigid_body'", angular_velocity=[1, 0, 0])
    # the reel's geometry describes the machine a fixed-length string hangs from: kept
    assert load_scene("fixed_length").reel.radius == 0.5 and not load_scene("fixed_length").has("reel")


def test_huge_integers_are_refused_not_converted():
    refused("fixed_length", "key 'body.mass'", mass=10**400)
    refused("fixed_length", "key 'initial.tip_velocity'", tip_velocity=[10**400, 0, 0])
    refused("fixed_length", "key 'string.elements'", elements=2**60)


# ------------------------------------------------------------------------------------------
# The public validation protocol of an effect's own rules
# ------------------------------------------------------------------------------------------
class Capped(Effect):
    """Refuses through the protocol it is given (a `models.schema.SceneChecks`)."""

    name = "capped"
    # only_with_effect without required_by: the owner is the effect that declares the key
    keys = {"capped": {"limit": Key("float", "positive", only_with_effect=True)}}

    def check(self, checks, d, effects):
        if self.name in effects and d["capped"]["limit"] > d["string"]["total_length"]:
            raise checks.fail("capped.limit", d["capped"]["limit"], "a limit <= string.total_length")
        if self.name in effects and d["body"]["mass"] > 5:
            raise checks.refuse("the cap needs a body of at most 5 kg", "body.mass")


def test_an_effect_refuses_through_the_public_checks_with_the_standard_wording():
    register_effect(Capped())
    try:
        d = load_scene("fixed_length").to_dict()
        d["effects"].append("capped")
        d["capped"] = {"limit": 50.0}
        refused(d, "bad.toml: key 'capped.limit' = 50.0 is invalid: allowed a limit <= string.total_length")
        d["capped"] = {"limit": 5.0}
        assert scene_from_dict(d).section("capped") == {"limit": 5.0}
        refused(dict(d, effects=d["effects"][:-1]), "key 'capped.limit' = 5.0 is only allowed with effect 'capped'")
        refused(d, "bad.toml (overridden): the cap needs a body of at most 5 kg", mass=6.0)
    finally:
        unregister_effect("capped")


@pytest.mark.parametrize("attrs, fragment", [
    ({"name": "Bad-Name"}, "lower-case identifier"),
    ({"name": "odd_kind", "keys": {"odd_kind": {"k": Key("float", "spd")}}}, "kind/rule 'float'/'spd'"),
    ({"name": "odd_range", "plausible": {"string.total_length": (0, 1)}}, "a key it does not own"),
    ({"name": "odd_section", "keys": {"t_end": {"k": Key("float")}}}, "section [t_end] is a top-level scene key"),
    ({"name": "heavy", "kinetic": lambda self, model: {}}, "overrides Effect.kinetic"),
])
def test_register_effect_refuses_what_the_schema_or_the_physics_paths_cannot_honour(attrs, fragment):
    cls = type("Probe", (Effect,), attrs)
    with pytest.raises(ValueError, match=fragment.replace("[", r"\[").replace("]", r"\]")):
        register_effect(cls())
    assert attrs["name"] not in EFFECTS


# ------------------------------------------------------------------------------------------
# Files read safely
# ------------------------------------------------------------------------------------------
def test_a_scene_with_a_utf8_bom_loads_like_the_file_without_it(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + (SCENE_DIR / "fixed_length.toml").read_bytes())
    assert load_scene(path) == load_scene("fixed_length")


@pytest.mark.parametrize("text", [
    "[" + ".".join(["a"] * 2000) + "]\nx = 1\n",  # nested tables
    "x = " + "[" * 2000 + "]" * 2000 + "\n",  # nested arrays (the parser recurses on these)
    "x = " + "{a = " * 2000 + "1" + "}" * 2000 + "\n",  # nested inline tables
    "[initial]\ndirection = [[[[[[1]]]]], 0, 0]\n",
], ids=["tables", "arrays", "inline_tables", "a_value"])
def test_deep_nesting_is_refused_without_a_recursion_error(tmp_path, text):
    path = tmp_path / "deep.toml"
    path.write_text(text)
    refused(path, str(path), "nested too deeply", "at most 4 levels")


def test_deep_nesting_in_a_mapping_or_an_override_is_refused():
    deep = 1.0
    for _ in range(2000):
        deep = [deep]
    refused({"name": "x", "t_end": deep}, "bad.toml", "nested too deeply")
    refused("fixed_length", "nested too deeply", direction=deep)


def test_a_device_is_refused_before_it_is_read(tmp_path):
    """A scene that is a symlink to /dev/zero was read until the memory ran out."""
    link = tmp_path / "zero.toml"
    link.symlink_to("/dev/zero")
    refused(link, str(link), "is a character device, not a regular file")


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    result = {}
    worker = threading.Thread(target=lambda: result.setdefault("msg", refused(fifo, "named pipe")), daemon=True)
    worker.start()
    worker.join(60)  # a hang guard, not a timing claim: open() on a FIFO blocks forever without a writer
    assert not worker.is_alive(), "load_scene blocked on a FIFO"
    assert "not a regular file" in result["msg"]


def test_a_directory_and_a_missing_file_are_named(tmp_path):
    refused(tmp_path, "is a directory", "give a scene name")
    refused(tmp_path / "nope.toml", "scene file not found")
    dangling = tmp_path / "dangling.toml"
    dangling.symlink_to(tmp_path / "gone.toml")
    refused(dangling, "is a symbolic link to", "gone.toml", "which does not exist")


def test_a_symlink_loop_is_reported_as_a_loop(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.symlink_to(b)
    b.symlink_to(a)
    msg = refused(a, str(a), "symbolic link loop")
    assert "not found" not in msg
    loop = tmp_path / "loop"  # without a suffix: not taken for a shipped scene's name
    loop.symlink_to(loop)
    refused(str(loop), "symbolic link loop")


def test_a_large_file_is_refused_by_its_size_without_being_opened(tmp_path, monkeypatch):
    """A 50 MB scene took 17-21 s to be refused; its size is now known before it is opened."""
    big = tmp_path / "big.toml"
    with open(big, "wb") as fh:
        fh.truncate(50 * 2**20)  # sparse: 50 MB by its size, nothing written
    class NoOpen:  # the os module as models.io sees it, without open()
        def __getattr__(self, name):
            if name == "open":
                pytest.fail("the file was opened")
            return getattr(os, name)

    monkeypatch.setattr(model_io, "os", NoOpen())
    refused(big, "52,428,800 bytes", f"more than the {MAX_SCENE_BYTES:,}", "a scene is a TOML file of a few kB")


def test_a_file_at_the_limit_is_read_and_one_byte_more_is_not(tmp_path):
    text = scene_text()
    padded = tmp_path / "padded.toml"
    padded.write_text(text + "#" * (MAX_SCENE_BYTES - len(text.encode()) - 1) + "\n")
    assert padded.stat().st_size == MAX_SCENE_BYTES and load_scene(padded) == load_scene("fixed_length")
    padded.write_text(text + "#" * (MAX_SCENE_BYTES - len(text.encode())) + "\n")
    refused(padded, "1,000,001 bytes")


def test_the_command_line_reports_a_fifo_as_an_error_not_a_hang(tmp_path):
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    proc = subprocess.run([sys.executable, "-m", "benchmark", "simulate", str(fifo)], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2 and "error:" in proc.stderr and "named pipe (FIFO)" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
