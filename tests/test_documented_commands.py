"""Every command README.md, integrators/README.md and models/README.md show, as written, with its
documented outcome.

* Default run: every concrete `python -m benchmark ...` command (and every row of the README's
  command table that is one) parses and passes its input checks, reaching the pipeline the docs
  say it runs, with the output they name (the pipelines replaced by recorders, in a copy of the
  repository's results/); every template row (``simulate SCENE --integrators NAME ...``) names a
  command and options that exist; the Python examples run and give their documented outcome;
  `list` runs for real.
* Slow (`-m slow`): every concrete command runs for real, as written, unshortened, in a copy of
  results/: it ends with its documented exit status, and results/ keeps every committed row it
  does not recompute.
"""

import importlib.util
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from _helpers import installed_plugin

ROOT = Path(__file__).resolve().parent.parent
DOCS = (ROOT / "README.md", ROOT / "integrators" / "README.md", ROOT / "models" / "README.md")
#: Commands that write elsewhere than runs.csv and take minutes: not run here.
NOT_RUN = {"check": "results/baseline/ only", "speed": "its --out file only", "stability": "results/stability/ only",
           "xval": "results/xval/ only", "reel-reversal": "results/reel_reversal/ and its cache only",
           "answer": "results/ (its cheapest.csv, README.md, figures) and the README's answer block",
           "verify": "writes nothing; tests/test_verify.py runs each documented verify",
           "work-rule": "results/work_rule.md only, and needs the numba floors kept outside the repository"}
#: Words of a template, not a command (an option to choose, a placeholder).
TEMPLATE = re.compile(r"\[|\]|\(|\.\.\.|COMMAND|HOST|NAME|FILE|TRAJ|SCENE|DIR\b|\bN\b|\bH\b|\bR\b|\bS\b|\bM\b")
SUBCOMMANDS = ("run", "check", "simulate", "figures", "speed", "stability", "xval", "reel-reversal", "orders", "energy",
               "answer", "verify", "work-rule", "list")
#: Commands whose real run is tested elsewhere because it needs a documented plugin installed
#: (tests/test_verify.py installs the models README's effect package and runs them).
NEEDS_EFFECT_EXAMPLE = re.compile(r"\btip_spring|\bverify\b")

#: The pipeline each documented command reaches, and the output the docs name for it (checked
#: in the default run; "" where the command has no output directory of its own).
REACHES = {"run": ("run_sweep", "out"), "check": ("run_check", ""), "speed": ("study:speed", "out"),
           "stability": ("study:stability map", "out"), "xval": ("study:xval", "out"),
           "reel-reversal": ("study:reel-reversal", "out"), "orders": ("study:orders", "out"),
           "energy": ("study:horizon", "out"), "answer": ("run_answer", "out"), "list": (None, "")}
#: The documented outputs, by command: where the docs say its results go.
DOCUMENTED_OUT = {"run --fresh": "results/grid", "run": "results/grid", "answer": "results",
                  "speed": "results/lgvi_speed.md", "stability": "results/stability", "xval": "results/xval",
                  "reel-reversal": "results/reel_reversal"}


def documented_commands() -> list[str]:
    """The benchmark's arguments of every `python -m benchmark ...` / `python3 -m benchmark ...`
    in the docs (inline code and code blocks), and of every row of a command table whose first
    cell is a benchmark command."""
    found = []
    for doc in DOCS:
        text = doc.read_text(encoding="utf-8")
        for m in re.finditer(r"python3? -m benchmark((?: [^`\n|&]+)?)", text):
            found.append(m.group(1).strip())
        for m in re.finditer(r"^\| `((?:" + "|".join(SUBCOMMANDS) + r")(?: [^`]*)?)` \|", text, flags=re.M):
            found.append(m.group(1).strip().replace("\\|", "|"))
    found = [c for c in dict.fromkeys(found) if c]
    return list(dict.fromkeys(e for c in found for e in _expansions(c)))


def _expansions(command: str) -> list[str]:
    """A row whose only template marks are optional groups ``[...]`` of concrete words is two
    commands, without and with them (``speed [--elements 10,40 --scenes a,b]``); any other row
    is itself."""
    bare = re.sub(r"\s*\[[^\]]*\]", "", command)
    full = command.replace("[", "").replace("]", "")
    if "[" in command and not TEMPLATE.search(bare) and not TEMPLATE.search(full):
        return [bare, full]
    return [command]


def concrete() -> list[str]:
    return [c for c in documented_commands() if not TEMPLATE.search(c)]


def templates() -> list[str]:
    return [c for c in documented_commands() if TEMPLATE.search(c) and c.split()[0] in SUBCOMMANDS]


def _site(tmp_path: Path) -> Path:
    """The integrators README's plugin (symplectic_euler), installed the way a package would be."""
    text = (ROOT / "integrators" / "README.md").read_text()
    code = re.search(r'```python\n("""my_stepper\.py.*?)```', text, flags=re.S).group(1)
    return installed_plugin(tmp_path / "site", "my_stepper", code, "symplectic_euler = my_stepper:SymplecticEuler")


def _user(tmp_path: Path) -> tuple[Path, dict]:
    """A user's working copy (the committed results/) and the environment with the plugin."""
    work = tmp_path / "user"
    shutil.copytree(ROOT / "results", work / "results", ignore=shutil.ignore_patterns("cache"))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(_site(tmp_path))]))
    return work, env


def test_the_docs_show_the_commands_this_test_runs():
    commands = concrete()
    assert {"answer --fresh", "answer --extended", "check", "check --update", "stability", "xval", "reel-reversal",
            "list"} <= set(commands)
    assert any("symplectic_euler" in c and "--out" in c for c in commands)  # the plugin example
    assert any(c.startswith("run --quick") and "--out" in c for c in commands)
    assert {"speed", "speed --elements 10,40,160,640 --scenes fixed_length,deployment"} <= set(commands)
    assert any(c.startswith("simulate ") for c in templates()) and any(c.startswith("check [") for c in templates())
    assert all(c.split()[0] in SUBCOMMANDS for c in commands), commands


#: Replaces every pipeline by a recorder and runs each command's checks (one process for all:
#: the plugin is registered through its entry point, as a user's would be).
_VALIDATE = r"""
import json, sys
from pathlib import Path
from reelbench.benchmark.cli import simulate
from reelbench.benchmark.cli.main import main
from reelbench.benchmark.studies import check, grid
calls = []
def recorder(name):
    def record(*args, **kw):
        out = kw.get("out")
        if name == "run_sweep":
            out = args[0].out
        calls.append({"pipeline": name, "out": None if out is None else str(out)})
        return 0
    return record
from reelbench.benchmark.core import study
study.run = lambda s, out, **kw: calls.append({"pipeline": "study:" + s.name, "out": str(out),
                                              "table": str(Path(out) / s.table)}) or 0
for module, name in ((grid, "run_sweep"), (simulate, "simulate"), (simulate, "draw_figures"), (check, "run_check")):
    setattr(module, name, recorder(name))
from reelbench.benchmark.answer import answer
answer.run_answer = lambda request, *a, **kw: recorder("run_answer")(out=request.out)
results = []
for args in json.loads(sys.argv[1]):
    calls.clear()
    rc = main(args)
    results.append({"args": args, "rc": rc, "calls": list(calls)})
print(json.dumps(results))
"""


def test_every_documented_command_parses_and_passes_its_checks(tmp_path):
    work, env = _user(tmp_path)
    commands = [c for c in concrete() if not NEEDS_EFFECT_EXAMPLE.search(c)]
    proc = subprocess.run([sys.executable, "-c", _VALIDATE, json.dumps([shlex.split(c) for c in commands])], cwd=work,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    xval_installed = all(importlib.util.find_spec(m) for m in ("moordyn", "mujoco"))
    for command, res in zip(commands, results):
        if command.startswith("xval") and not xval_installed:  # documented: needs the [xval] extra
            assert res["rc"] == 2 and "pip install 'reelbench[xval]'" in proc.stderr
            continue
        assert res["rc"] == 0, (command, proc.stderr[-3000:])
        args = res["args"]
        pipeline, _ = REACHES[args[0]]
        if pipeline is None:
            continue
        assert [c["pipeline"] for c in res["calls"]] == [pipeline], (command, res)
        out, table = res["calls"][0]["out"], res["calls"][0].get("table")
        # where it writes: its directory, and a study's Markdown beside its table (the speed tables)
        places = [Path(p) for p in (out,) if p is not None] + ([Path(table).with_suffix(".md")] if table else [])
        if "--out" in args:
            assert Path(args[args.index("--out") + 1]) in places, (command, out)
        elif command in DOCUMENTED_OUT or args[0] in DOCUMENTED_OUT:
            assert Path(DOCUMENTED_OUT.get(command, DOCUMENTED_OUT[args[0]])) in places, (command, out)
    assert not any(p.name == ".reelbench.lock" for p in work.rglob("*"))  # no pipeline ran


def test_every_documented_template_names_options_that_exist():
    from reelbench.benchmark.cli.main import parser

    commands = parser()._subparsers._group_actions[0].choices
    for template in templates():
        name, *rest = template.split()
        options = set(commands[name]._option_string_actions)
        shown = {w.strip("[]()|") for w in rest if w.strip("[]()|").startswith("--")}
        assert shown and shown <= options or not shown, (template, shown - options)


def _python_block(doc: Path, starts: str) -> str:
    text = doc.read_text(encoding="utf-8")
    return next(b for b in re.findall(r"```python\n(.*?)```", text, flags=re.S) if b.startswith(starts))


def test_the_readme_example_runs_and_finishes_as_documented():
    code = _python_block(ROOT / "README.md", "from reelbench.models import load_scene")
    space: dict = {}
    exec(compile(code, "README.md: Using it", "exec"), space)
    traj, df = space["traj"], space["df"]
    assert traj.status == "ok", traj.reason  # the comment's outcome
    assert {"t", "energy", "work", "pi3", "orthogonality_error", "deployed_length"} <= set(df.columns)
    # and the step it warns about does stop with "diverged"
    from reelbench.integrators import get_integrator

    assert get_integrator("lgvi").solve(space["scene"], t_end=1.0, dt=0.005).status == "diverged"


def test_the_scene_file_example_of_models_readme_runs(tmp_path, monkeypatch):
    from reelbench.models.scene import SCENE_DIR

    code = _python_block(ROOT / "models" / "README.md", "from reelbench.models import load_scene")
    assert "my_scene.toml" in code
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my_scene.toml").write_text((SCENE_DIR / "fixed_length.toml").read_text())  # "a file of your own"
    space: dict = {}
    exec(compile(code, "models/README.md: Scene files", "exec"), space)
    assert space["scene"].body.mass == 2


def test_list_runs_as_documented(tmp_path):
    work, env = _user(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "benchmark", "list"], cwd=work, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0 and "symplectic_euler" in proc.stdout and "scenes:" in proc.stdout, proc.stderr


# ------------------------------------------------------------------------------------------
# Slow: every concrete command for real, as written
# ------------------------------------------------------------------------------------------
#: Documented exit status of each command run as written on a fresh copy (0: it does its job).
OUTCOME = {"check": 0, "check --update": 0}


@pytest.mark.slow
@pytest.mark.parametrize("command", [c for c in concrete() if not NEEDS_EFFECT_EXAMPLE.search(c)])
def test_every_documented_command_runs_as_written(tmp_path, command):
    """As written, unshortened (minutes each; the default sweep, the stability map, xval and the
    full check take the longest): its documented exit status, no traceback, and every committed
    row of results/grid/runs.csv it does not recompute kept."""
    work, env = _user(tmp_path)
    args = shlex.split(command)
    if args[0] == "xval":
        pytest.importorskip("moordyn")
        pytest.importorskip("mujoco")
    committed = pd.read_csv(work / "results" / "grid" / "runs.csv")
    scratch = [args[k + 1] for k, a in enumerate(args[:-1]) if a == "--out" and not args[k + 1].startswith("results")]
    started = time.time()  # a scratch --out is the user's (/tmp/...): written, never deleted by the test
    proc = subprocess.run([sys.executable, "-m", "benchmark", *args], cwd=work, env=env, capture_output=True, text=True,
                          timeout=3600)
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert proc.returncode == OUTCOME.get(command, 0), (command, proc.stderr[-3000:])
    after = pd.read_csv(work / "results" / "grid" / "runs.csv")
    kept = committed.merge(after, on=["scene", "integrator", "setting"], suffixes=("", "_after"))
    assert len(kept) == len(committed), f"{command}: {len(committed) - len(kept)} committed rows lost"
    for d in scratch:
        assert all((Path(d) / f).stat().st_mtime >= started for f in ("runs.csv", "README.md")), command
