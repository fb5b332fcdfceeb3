"""The command line refuses nonsense at once: every bad input below gets exit
status 2 and one `error:` message naming the input, the problem and the fix, no traceback,
before any work -- and, where no JAX is needed, without importing it."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from reelbench.benchmark.cli.main import main

ROOT = Path(__file__).resolve().parent.parent
TINY = ["--scenes", "fixed_length", "--integrators", "lgvi", "--t-end", "0.02", "--no-figures"]


@pytest.fixture
def files(tmp_path):
    scene = (ROOT / "models" / "scenes" / "fixed_length.toml").read_text()
    (tmp_path / "garbage.toml").write_bytes(b"\x00\xff\xfe binary \x89PNG")
    (tmp_path / "garbage.npz").write_bytes(b"\x00\xff\xfe binary \x89PNG")
    (tmp_path / "afile").write_text("x")
    (tmp_path / "noname.toml").write_text("\n".join(l for l in scene.splitlines() if not l.startswith("name")))
    (tmp_path / "strmass.toml").write_text("\n".join('mass = "1.0"' if l.startswith("mass ") else l
                                                     for l in scene.splitlines()))
    return tmp_path


# (arguments, fragments the message must contain); {d} is the test's directory
CASES = [
    (["run", "--out", "{d}/afile"], ["--out", "afile", "is a file, not a directory"]),
    (["run", "--out", "/dev/null/sub"], ["--out", "/dev/null/sub", "not writable"]),
    (["run", "--jobs", "0"], ["argument --jobs", "'0'", "integer >= 1"]),
    (["run", "--jobs", "x"], ["argument --jobs", "'x' is not an integer"]),
    (["run", "--repeats", "0"], ["argument --repeats", "integer >= 1"]),
    (["run", "--repeats", "-1"], ["argument --repeats", "integer >= 1"]),
    (["run", "--horizon", "-5"], ["argument --horizon", ">= 0"]),
    (["run", "--dts", "abc"], ["argument --dts", "'abc' is not a number"]),
    (["run", "--dts", "11", "--out", "{d}/o"], ["dt = 11 s is longer than the run", "allowed: 0 < dt <= t_end"]),
    (["run", "--rtols", "2"], ["argument --rtols", "1e-14 <= tolerance < 1"]),
    (["run", "--t-end", "-1"], ["argument --t-end", "> 0"]),
    (["run", "--t-end", "nan"], ["argument --t-end", "not a finite number"]),
    (["run", "--set", "mass"], ["--set 'mass'", "KEY=VALUE"]),
    (["run", "--set", "mass=1e300", "--out", "{d}/o"], ["'body.mass'", "implausible", "[1e-09, 1e+09]"]),
    (["run", "--set", "axial_stiffness=1e308", "--out", "{d}/o"], ["'string.axial_stiffness'", "implausible"]),
    (["run", "--set", "elements=1000000", "--out", "{d}/o"], ["'string.elements'", "implausible"]),
    (["run", "--set", "t_end=1e12", "--out", "{d}/o"], ["'t_end'", "implausible"]),
    (["run", "--set", "elements=0", "--out", "{d}/o"], ["'string.elements'", "integer >= 1"]),
    (["run", "--executor", "dask"], ["--executor dask needs --scheduler"]),
    (["run", "--scheduler", "tcp://x:1"], ["--scheduler is only used with --executor dask"]),
    (["simulate", "{d}"], ["is a directory", "give a scene name"]),
    (["simulate", "nosuch"], ["unknown scene 'nosuch'"]),
    (["simulate", "fixed_length", "--dt", "1e-300", "--out", "{d}/t.npz"], ["1e+301 steps", "raise --dt"]),
    (["simulate", "fixed_length", "--dt", "0.002", "--rtol", "1e-6"], ["argument --rtol: not allowed with argument --dt"]),
    (["simulate", "fixed_length", "--atol", "1e-8"], ["--atol needs --rtol"]),
    (["simulate", "fixed_length", "--dt", "0"], ["argument --dt", "> 0"]),
    (["simulate", "fixed_length", "--t-end", "1e12", "--dt", "0.01"], ["'t_end'", "implausible"]),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", "{d}"], ["is a directory", "give a file name"]),
    (["simulate", "fixed_length", "--dt", "1e-3", "--t-end", "1e5", "--set", "elements=2000", "--out", "{d}/t.npz"],
     ["saved points", "GiB", "raise --save-every"]),
    (["simulate", "{d}/garbage.toml"], ["garbage.toml", "not a text file"]),
    (["simulate", "{d}/noname.toml"], ["noname.toml", "missing key 'name': allowed a string"]),
    (["simulate", "{d}/strmass.toml"], ["strmass.toml", "'body.mass' = \"1.0\"", "without quotes"]),
    (["figures", "{d}/missing.npz"], ["missing.npz: no such file"]),
    (["figures", "{d}/garbage.npz"], ["garbage.npz: not a trajectory file"]),
    (["figures", "{d}"], ["is not a file"]),
    (["speed", "--elements", "0"], ["argument --elements", "integer >= 1"]),
    (["speed", "--elements", "abc"], ["argument --elements", "'abc' is not an integer"]),
    (["speed", "--elements", "1000000"], ["'string.elements'", "implausible"]),
    (["reel-reversal", "--integrators", "rk45"], ["--integrators: 'rk45' has no step list", "allowed: lgvi"]),
    (["reel-reversal", "--t-end", "0.5"], ["--t-end = 0.5 is invalid", "multiple of 0.08 s"]),
    (["reel-reversal", "--cache-dir", "{d}/afile"], ["--cache-dir", "is a file, not a directory"]),
    (["stability", "--jobs", "-1"], ["argument --jobs", ">= 0"]),
    (["stability", "--out", "{d}/afile"], ["is a file, not a directory"]),
]


@pytest.mark.parametrize("args, fragments", CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_input_exit_2_with_a_message(files, capsys, args, fragments):
    rc = main([a.format(d=files) for a in args])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert "error: " in line, err  # argparse's lines read "prog: error: ...", ours "error: ..."
    for f in fragments:
        assert f in line, (f, line)


def test_check_outside_the_repository_says_where_to_run_it(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["check"]) == 2
    err = capsys.readouterr().err
    assert "repository's root directory" in err and "--baseline" in err and "--update" not in err


def test_figures_refuses_a_trajectory_of_another_scene(tmp_path, capsys):
    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    traj = get_integrator("lgvi").solve(load_scene("fixed_length", elements=1), t_end=0.02, dt=0.01)
    traj.save(tmp_path / "t.npz")
    assert main(["figures", str(tmp_path / "t.npz"), "--scenes", "deployment"]) == 2
    err = capsys.readouterr().err
    assert "does not fit scene 'deployment'" in err and "recorded: 'fixed_length'" in err


def test_every_option_is_documented_with_its_default(capsys):
    """Every option of every command has a help line in its --help, and each one with a default
    to show (not None, not a flag's False) shows it as "(default: VALUE)"."""
    import argparse

    from reelbench.benchmark.cli.main import parser

    p = parser()
    sub = next(a for a in p._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, sp in sub.choices.items():
        assert main([name, "--help"]) == 0
        text = " ".join(capsys.readouterr().out.split())
        for action in sp._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, (name, action.dest)
            assert all(o in text for o in action.option_strings), (name, action.option_strings)
            if action.default not in (None, False, argparse.SUPPRESS):
                assert f"(default: {action.default})" in text, (name, action.dest, action.default)
    assert main(["run", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for expected in ("--out OUT", "(default: results/grid)", "--repeats", "(default: 3)", "--horizon", "--fresh"):
        assert expected in text, expected
    assert main(["simulate", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: lgvi)" in text and "(default: 0.02)" in text and "current directory" in text


PROBE = textwrap.dedent("""
    import json, sys, time
    t0 = time.perf_counter()
    from reelbench.benchmark.cli.main import main
    rc = main(json.loads(sys.argv[1]))
    heavy = sorted(m for m in ("jax", "diffrax", "pandas", "matplotlib", "reelbench.integrators", "scipy.integrate")
                   if m in sys.modules)
    print(json.dumps({"rc": rc, "heavy": heavy, "seconds": time.perf_counter() - t0}))
""")


@pytest.mark.parametrize("args", [["--help"], ["run", "--help"], ["run", "--jobs", "0"],
                                  ["run", "--set", "mass=1e300"], ["run", "--dts", "11"],
                                  ["simulate", "fixed_length", "--dt", "1e-300"], ["simulate", "/tmp"],
                                  ["figures", "missing.npz"], ["speed", "--elements", "0"],
                                  ["run", "--out", "/dev/null/x"]])
def test_help_and_refusals_do_not_import_jax(args):
    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args)], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["rc"] == (0 if "--help" in args else 2), out.stderr
    assert res["heavy"] == [], res


def test_simulate_and_figures_write_next_to_the_user(tmp_path, monkeypatch, capsys):
    """Not into the repository's tracked results/: into the current directory, or --out."""
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "fixed_length", "--set", "elements=1", "--t-end", "0.04", "--dt", "0.01"]) == 0
    assert (tmp_path / "simulate_fixed_length_lgvi.npz").exists()
    assert (tmp_path / "simulate_fixed_length_lgvi.csv").exists()
    assert main(["figures", "simulate_fixed_length_lgvi.npz", "--set", "elements=1"]) == 0
    assert (tmp_path / "simulate_fixed_length_lgvi.png").exists()
    assert main(["figures", "simulate_fixed_length_lgvi.npz", "--set", "elements=1", "--out", "sub/f.png"]) == 0
    assert (tmp_path / "sub" / "f.png").exists()
    assert not (tmp_path / "results").exists()
    # a trajectory elsewhere: its figure goes beside it, not into the current directory
    (tmp_path / "runs").mkdir()
    (tmp_path / "simulate_fixed_length_lgvi.npz").rename(tmp_path / "runs" / "t.npz")
    assert main(["figures", "runs/t.npz", "--set", "elements=1"]) == 0
    assert (tmp_path / "runs" / "t.png").exists() and not (tmp_path / "t.png").exists()


def test_size_estimate_warns_about_a_long_run_and_refuses_what_cannot_fit():
    from reelbench.benchmark.core import options
    from reelbench.models import load_scene

    said = []
    big = load_scene("fixed_length", elements=2000)
    size = options.check_size(big, 100.0, 0.02, 1e-5, warn=said.append, what="big")
    assert size["steps"] == pytest.approx(1e7) and size["seconds"] > options.TIME_WARN
    assert len(said) == 1 and said[0].startswith("warning: big takes 1e+07 steps; estimated"), said
    said.clear()
    options.check_size(load_scene("fixed_length"), 10.0, 0.02, 0.005, warn=said.append)
    assert said == []  # the paper's scene at its step: nothing to say
    with pytest.raises(options.UsageError, match="saved points"):
        options.check_size(big, 1e5, 1e-3, None)
    with pytest.raises(options.UsageError, match="steps of dt"):
        options.check_size(big, 10.0, 0.02, 1e-9)


# ------------------------------------------------------------------------------------------
# runs that would do nothing, or nothing useful, and exit 0: refused before any work, and a
# refused command leaves no --out behind
# ------------------------------------------------------------------------------------------
@pytest.fixture
def no_pipeline(monkeypatch):
    """Every pipeline replaced by a failure: a bad input that got through would start work."""
    from reelbench.benchmark.cli import simulate
    from reelbench.benchmark.core import study
    from reelbench.benchmark.studies import check, grid

    monkeypatch.setattr(study, "run", lambda s, *a, **k: pytest.fail(f"reached the study {s.name}"))
    for module, name in ((grid, "run_sweep"), (simulate, "simulate"), (simulate, "draw_figures"), (check, "run_check")):
        monkeypatch.setattr(module, name, lambda *a, _n=name, **k: pytest.fail(f"reached the pipeline {_n}"))


NOTHING = [
    (["run", "--scenes", "fixed_length", "--dts", "1e308", "--out", "{d}/o"], ["--dts", "1e+308", "longer than the run"]),
    (["run", "--scenes", "fixed_length", "--dts", "0.02", "--t-end", "0.01", "--out", "{d}/o"],
     ["--t-end = 0.01 s is shorter than", "give --t-end >= 0.02"]),
    (["run", "--scenes", "fixed_length", "--rtols", "1e-300", "--out", "{d}/o"], ["--rtols", "1e-14 <= tolerance"]),
    (["simulate", "fixed_length", "--rtol", "1e-300", "--out", "{d}/o/t.npz"], ["--rtol", "1e-14 <= tolerance"]),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", ""], ["--out is empty", "give a file name"]),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", "{d}/o/t.npz", "--save-every", "100"],
     ["--save-every 100", "give a save interval"]),
    (["simulate", "fixed_length", "--integrators", "nosuch", "--dt", "0.01", "--out", "{d}/o/t.npz"],
     ["unknown integrator 'nosuch'"]),
    (["speed", "--dt", "1e300", "--out", "{d}/o/speed.md"], ["t_end", "implausible"]),
    (["speed", "--out", ""], ["--out is empty"]),
    (["stability", "--scenes", "nosuch", "--out", "{d}/o"], ["no stability case", "nosuch"]),
    (["stability", "--integrators", "nosuch", "--out", "{d}/o"], ["unknown integrator 'nosuch'"]),
    (["stability", "--out", ""], ["--out is empty"]),
    (["xval", "--t-end", "1e12", "--out", "{d}/o"], ["'t_end'", "implausible"]),
    (["xval", "--scenes", "deployment", "--out", "{d}/o"], ["cannot translate scene 'deployment'"]),
    (["reel-reversal", "--integrators", "nosuch", "--cache-dir", "{d}/o"], ["--integrators", "'nosuch'"]),
    (["run", "--integrators", "nosuch", "--quick", "--out", "{d}/o"], ["unknown integrator 'nosuch'"]),
    (["run", "--quick", "--out", ""], ["--out is empty"]),
    (["check", "--update", "--allow-new", "lgvi"], ["--allow-new is for a check against the baseline"]),
]


@pytest.mark.parametrize("args, fragments", NOTHING, ids=[" ".join(a) for a, _ in NOTHING])
def test_a_run_that_would_do_nothing_is_refused_and_creates_nothing(tmp_path, capsys, no_pipeline, args, fragments):
    rc = main([a.format(d=tmp_path) for a in args])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    line = err.strip().splitlines()[-1]
    for f in fragments:
        assert f in line, (f, line)
    assert not (tmp_path / "o").exists()  # a refused command leaves no --out behind


def test_figures_of_a_trajectory_without_a_finite_point_is_refused(tmp_path, capsys):
    import numpy as np

    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    traj = get_integrator("lgvi").solve(load_scene("fixed_length", elements=1), t_end=0.02, dt=0.01)
    traj.x = np.full_like(np.asarray(traj.x), np.nan)
    traj.save(tmp_path / "nan.npz")
    assert main(["figures", str(tmp_path / "nan.npz"), "--set", "elements=1", "--out", str(tmp_path / "f.png")]) == 2
    err = capsys.readouterr().err
    assert "no finite point" in err and "nothing to draw" in err, err
    assert not (tmp_path / "f.png").exists()


# ------------------------------------------------------------------------------------------
# 150+ bad inputs: every option of every command with the values people get wrong
# ------------------------------------------------------------------------------------------
POSITIVE_INT = ["0", "-1", "x", "", "1.5", "1e3"]
NONNEGATIVE_INT = ["-1", "x", "", "2.5"]
POSITIVE_FLOAT = ["0", "-1", "nan", "inf", "x", ""]
TOLERANCE = ["0", "1", "2", "1e-300", "nan", "x"]
#: (command and the arguments that make it otherwise valid, option, bad values)
OPTIONS = [
    (["run", "--quick", "--out", "{d}/o"], "--jobs", POSITIVE_INT),
    (["run", "--quick", "--out", "{d}/o"], "--repeats", POSITIVE_INT),
    (["run", "--quick", "--out", "{d}/o"], "--horizon", ["-1", "nan", "inf", "x", ""]),
    (["run", "--quick", "--out", "{d}/o"], "--dts", POSITIVE_FLOAT + ["1e308", ","]),
    (["run", "--quick", "--out", "{d}/o"], "--rtols", TOLERANCE + [","]),
    (["run", "--quick", "--out", "{d}/o"], "--t-end", POSITIVE_FLOAT + ["1e12", "0.001"]),
    (["simulate", "fixed_length", "--out", "{d}/o/t.npz"], "--dt", POSITIVE_FLOAT + ["1e-300"]),
    (["simulate", "fixed_length", "--out", "{d}/o/t.npz"], "--rtol", TOLERANCE),
    (["simulate", "fixed_length", "--rtol", "1e-6", "--out", "{d}/o/t.npz"], "--atol", POSITIVE_FLOAT),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", "{d}/o/t.npz"], "--t-end", POSITIVE_FLOAT + ["1e12"]),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", "{d}/o/t.npz"], "--save-every", POSITIVE_FLOAT + ["1e3"]),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", "{d}/o/t.npz"], "--integrators", ["nosuch", "", "../x"]),
    (["simulate", "fixed_length", "--dt", "0.01", "--out", "{d}/o/t.npz"], "--set",
     ["mass", "=1", "mass=-1", "mass=1e300", "elements=0", "elements=1e6", "nosuch=1", "name=../x", "t_end=1e12",
      "box=[0,0,0]", "direction=[1e200,0,1e200]", "deployed_length=1e-300", "control_moment=5"]),
    (["speed", "--out", "{d}/o/s.md"], "--elements", POSITIVE_INT + ["1000000"]),
    (["speed", "--out", "{d}/o/s.md"], "--steps", POSITIVE_INT),
    (["speed", "--out", "{d}/o/s.md"], "--repeats", POSITIVE_INT),
    (["speed", "--out", "{d}/o/s.md"], "--dt", POSITIVE_FLOAT + ["1e300"]),
    (["speed", "--out", "{d}/o/s.md"], "--autodiff-max-n", POSITIVE_INT),
    (["speed", "--out", "{d}/o/s.md"], "--integrators", ["nosuch", "rk45", ","]),
    (["speed", "--out", "{d}/o/s.md"], "--scenes", ["nosuch", ","]),
    (["stability", "--out", "{d}/o"], "--jobs", NONNEGATIVE_INT),
    (["stability", "--out", "{d}/o"], "--scenes", ["nosuch", ","]),
    (["stability", "--out", "{d}/o"], "--integrators", ["nosuch", ","]),
    (["xval", "--out", "{d}/o"], "--elements", POSITIVE_INT + ["1", "5"]),
    (["xval", "--out", "{d}/o"], "--t-end", POSITIVE_FLOAT + ["1e12"]),
    (["xval", "--out", "{d}/o"], "--scenes", ["nosuch", "deployment", ""]),
    (["reel-reversal", "--cache-dir", "{d}/o"], "--elements", POSITIVE_INT),
    (["reel-reversal", "--cache-dir", "{d}/o"], "--t-end", POSITIVE_FLOAT + ["0.5"]),
    (["reel-reversal", "--cache-dir", "{d}/o"], "--jobs", NONNEGATIVE_INT),
    (["reel-reversal", "--cache-dir", "{d}/o"], "--integrators", ["nosuch", "rk45"]),
    (["check", "--baseline", "{d}/b.csv"], "--factor", ["1", "0.5", "nan", "x", ""]),
    (["check", "--baseline", "{d}/b.csv"], "--order-margin", ["-1", "nan", "x"]),
    (["check", "--baseline", "{d}/b.csv"], "--jobs", POSITIVE_INT),
    (["check", "--baseline", "{d}/b.csv"], "--integrators", ["nosuch"]),
    (["check", "--baseline", "{d}/b.csv", "--integrators", "lgvi"], "--allow-new", ["nosuch", ","]),
]
BULK = [(base, option, value) for base, option, values in OPTIONS for value in values]
#: A message names the fix: what is allowed, what to give, or what to do.
FIX = ("allowed", "available:", "give", "e.g.", "raise", "shorten", "expected", "add ", "remove", "use ", "run ",
       "pip install")


def test_more_than_150_bad_inputs_are_each_refused_with_exit_2_and_the_fix(tmp_path, capsys, no_pipeline):
    assert len(BULK) >= 150, len(BULK)
    from reelbench.benchmark.studies import check

    check.write_baseline(check.to_table.__globals__["pd"].DataFrame(columns=check.COLUMNS), tmp_path / "b.csv")
    failures = []
    for base, option, value in BULK:
        args = [a.format(d=tmp_path) for a in base] + [option, value]
        try:
            rc = main(args)
        except BaseException as exc:  # a pipeline reached (pytest.fail) or a crash: recorded, the others still run
            rc = f"{type(exc).__name__}: {exc}"
        err = capsys.readouterr().err.strip()
        line = err.splitlines()[-1] if err else ""
        key = value.split("=")[0] if option == "--set" else None  # an override is named by its key
        named = (option in line or option.lstrip("-").replace("-", "_") in line or repr(value) in line
                 or bool(value and value in line) or bool(key and key in line))
        if rc != 2 or "Traceback" in err or "error: " not in line or not named or not any(f in line for f in FIX):
            failures.append((args[len(base):], rc, line))
    assert not failures, "\n".join(map(str, failures))
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args", [["simulate", "fixed_length", "--integrators", "nosuch", "--dt", "0.01"],
                                  ["run", "--integrators", "nosuch", "--quick", "--out", "{d}/never"],
                                  ["stability", "--scenes", "nosuch", "--out", "{d}/never"],
                                  ["check", "--factor", "1"], ["check", "--integrators", "nosuch"],
                                  ["check", "--baseline", "/nonexistent/drift.csv"],
                                  ["run", "--rtols", "1e-300"], ["speed", "--dt", "1e300"],
                                  ["xval", "--t-end", "1e12", "--out", "{d}/never"]])
def test_refusals_that_need_the_registry_or_a_study_do_not_import_jax(tmp_path, args):
    """The registry lists names and capabilities, and the studies' modules load, without JAX
    (the methods and metrics import it on first use), so these refusals are as quick as the rest."""
    argv = [a.format(d=tmp_path) for a in args]
    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(argv)], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["rc"] == 2, out.stderr
    assert not {"jax", "diffrax", "matplotlib", "scipy.integrate"} & set(res["heavy"]), res
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("args, fragments", [
    (["simulate", "fixed_length"], ["lgvi needs a setting", "give --dt (a fixed step)"]),
    (["simulate", "fixed_length", "--integrators", "dop853"], ["dop853 needs a setting", "give --rtol (a tolerance)"]),
    (["simulate", "fixed_length", "--integrators", "tsit5"], ["give --dt (a fixed step) or --rtol (a tolerance)"]),
    (["simulate", "fixed_length", "--integrators", "dop853", "--dt", "0.01"], ["--dt: dop853 is adaptive"]),
    (["simulate", "fixed_length", "--rtol", "1e-6"], ["--rtol: lgvi is a fixed-step method", "give --dt"]),
    (["simulate", "fixed_length", "--dt", "5", "--t-end", "0.1", "--save-every", "0.1"],
     ["--dt 5 is longer than the run", "give --dt <= t_end"]),
    (["run", "--scenes", "fixed_length", "--t-end", "1e5", "--set", "elements=2000", "--dts", "0.01", "--out", "{d}/o"],
     ["saved points", "shorten --t-end"]),
])
def test_messages_name_the_option_the_user_types(tmp_path, capsys, no_pipeline, args, fragments):
    assert main([a.format(d=tmp_path) for a in args]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    for f in fragments:
        assert f in line, (f, line)
    assert "--save-every" not in line or args[0] == "simulate"  # run has no --save-every to raise



def test_figures_does_not_follow_a_scene_path_recorded_in_a_trajectory(tmp_path, capsys):
    """The scene name stored in a .npz is data: a path there (to a FIFO, say) is never opened."""
    import os

    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    traj = get_integrator("lgvi").solve(load_scene("fixed_length", elements=1), t_end=0.02, dt=0.01)
    os.mkfifo(tmp_path / "pipe.toml")
    traj.scene_name = str(tmp_path / "pipe.toml")
    traj.save(tmp_path / "t.npz")
    assert main(["figures", str(tmp_path / "t.npz"), "--out", str(tmp_path / "f.png")]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "which is not a scene name: give --scenes" in line, line
