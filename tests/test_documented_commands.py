"""Every `python -m benchmark ...` command the README and integrators/README.md show, run as a
user would (from a copy of the repository's results/), leaves every committed row of
results/runs.csv in place. A sweep is cut to `--quick` on one scene (and its scratch --out sent
to a temporary directory); the studies that never touch runs.csv and take minutes (check, speed,
stability, xval, reel-reversal) are named, not run. The sweeps skip their figures and energy
study: those never touch runs.csv (tests/test_resume_merge.py runs them)."""

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from _helpers import installed_plugin

ROOT = Path(__file__).resolve().parent.parent
DOCS = (ROOT / "README.md", ROOT / "integrators" / "README.md")
#: Commands that write elsewhere than runs.csv and take minutes: not run here.
NOT_RUN = {"check": "results/baseline/ only", "speed": "its --out file only", "stability": "results/stability/ only",
           "xval": "results/xval/ only", "reel-reversal": "stdout and its cache only",
           "verify": "writes nothing; tests/test_verify.py runs each documented verify"}
#: Words of a template, not a command (an option to choose, a placeholder).
TEMPLATE = re.compile(r"\[|\]|\.\.\.|COMMAND|HOST|NAME|FILE|TRAJ|DIR\b|\bN\b")


def documented_commands() -> list[str]:
    """The benchmark's arguments of every `python -m benchmark ...` / `python3 -m benchmark ...`
    in the docs (inline code and code blocks), and of the command table's `run ...` rows."""
    found = []
    for doc in DOCS:
        text = doc.read_text(encoding="utf-8")
        for m in re.finditer(r"python3? -m benchmark((?: [^`\n|&]+)?)", text):
            found.append(m.group(1).strip())
        for m in re.finditer(r"^\| `(run [^`]*)` \|", text, flags=re.M):
            found.append(m.group(1).strip())
    return list(dict.fromkeys(found))


def _site(tmp_path: Path) -> Path:
    """The integrators README's plugin (symplectic_euler), installed the way a package would be."""
    text = (ROOT / "integrators" / "README.md").read_text()
    code = re.search(r'```python\n("""my_stepper\.py.*?)```', text, flags=re.S).group(1)
    return installed_plugin(tmp_path / "site", "my_stepper", code, "symplectic_euler = my_stepper:SymplecticEuler")


def as_run(args: list[str], scratch: Path) -> list[str]:
    """A documented sweep made cheap: --quick on one scene, in this process, without figures or
    the energy study (they never touch runs.csv), and a scratch --out (any outside results/) sent
    to ``scratch``."""
    args = list(args)
    if "--out" in args:
        k = args.index("--out") + 1
        if not args[k].startswith("results"):
            args[k] = str(scratch)
    if "--quick" not in args:
        args.append("--quick")
    if "--scenes" not in args:
        args += ["--scenes", "fixed_length"]
    return args + ["--no-figures", "--executor", "serial"]


def test_the_docs_show_the_commands_this_test_runs():
    commands = documented_commands()
    runs = [c for c in commands if c.split()[:1] == ["run"] and not TEMPLATE.search(c)]
    assert "run --fresh" in runs  # the main job
    assert any("symplectic_euler" in c and "--out" in c for c in runs)  # the plugin example, into a scratch dir
    assert any(c.startswith("run --quick") and "--out" in c for c in runs)


def _scratch(args: list[str]) -> bool:
    """A sweep whose --out is a scratch directory (not results/): it cannot touch results/."""
    return "--out" in args and not args[args.index("--out") + 1].startswith("results")


def _run_documented(tmp_path: Path, everything: bool) -> list:
    work = tmp_path / "user"
    shutil.copytree(ROOT / "results", work / "results", ignore=shutil.ignore_patterns("cache"))
    committed = pd.read_csv(ROOT / "results" / "runs.csv")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(_site(tmp_path))]))
    ran = []
    for n, command in enumerate(documented_commands()):
        args = shlex.split(command)
        if not args or TEMPLATE.search(command) or args[0].startswith("-") or args[0] in NOT_RUN:
            continue
        if args[0] == "run":
            if _scratch(args) and not everything:
                ran.append(("scratch", None))
                continue
            args = as_run(args, tmp_path / f"scratch{n}")
        proc = subprocess.run([sys.executable, "-m", "benchmark", *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=600)
        # refused (exit 2, "error: ...") or done (0): never a traceback
        assert proc.returncode in (0, 2) and "Traceback" not in proc.stderr, (args, proc.stderr[-3000:])
        if proc.returncode == 2:
            assert proc.stderr.startswith("error:"), (args, proc.stderr[-2000:])
        ran.append((args[0], proc.returncode))
        after = pd.read_csv(work / "results" / "runs.csv")
        kept = committed.merge(after, on=["scene", "integrator", "setting"], suffixes=("", "_after"))
        assert len(kept) == len(committed), f"{command}: {len(committed) - len(kept)} committed rows lost"
        for col in ("status", "steps", "energy_error", "run_time"):
            pd.testing.assert_series_equal(kept[col], kept[f"{col}_after"], check_names=False, obj=f"{command}: {col}")
    assert (work / "results" / "runs.csv").read_bytes() == (ROOT / "results" / "runs.csv").read_bytes()
    assert not (work / "README.md").exists()  # the answer block is written only into the repository's README
    return ran


def test_every_documented_command_into_results_keeps_the_committed_rows(tmp_path):
    """The sweeps that would write into results/ (refused unless they are the default sweep or
    name --out results) and the cheap commands; the scratch sweeps write elsewhere by their --out."""
    ran = _run_documented(tmp_path, everything=False)
    assert ("run", 2) in ran and ("list", 0) in ran and ("scratch", None) in ran, ran


@pytest.mark.slow
def test_every_documented_command_runs_and_keeps_the_committed_rows(tmp_path):
    """All of them, the scratch sweeps (the plugin example, the quick example) included: they
    finish, and results/ keeps every committed row."""
    ran = _run_documented(tmp_path, everything=True)
    assert ("run", 0) in ran and ("list", 0) in ran and ("scratch", None) not in ran, ran


@pytest.mark.parametrize("given, expected", [
    (["run", "--fresh"], ["run", "--fresh", "--quick", "--scenes", "fixed_length"]),
    (["run", "--quick", "--out", "/tmp/x"], ["run", "--quick", "--out", "S", "--scenes", "fixed_length"]),
    (["run", "--out", "results"], ["run", "--out", "results", "--quick", "--scenes", "fixed_length"]),
])
def test_a_documented_sweep_is_cut_down_and_its_scratch_out_redirected(given, expected):
    assert as_run(given, Path("S")) == expected + ["--no-figures", "--executor", "serial"]
