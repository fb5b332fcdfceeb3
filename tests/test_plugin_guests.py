"""A plugin is a guest: visible where its user asks for it, absent where they did not.

With the integrators README's example package installed (a temporary site directory), the
default sweep and the stability map keep to the project's own methods, a run that would add the
plugin's rows to the committed results/ is refused in one line that names it, `list` marks it
with its package and version, and its rows' provenance follows its package and its source.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from test_verify import install_documented

ROOT = Path(__file__).resolve().parent.parent
NAME = "symplectic_euler"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    site = tmp_path_factory.mktemp("guest") / "site"
    install_documented(ROOT / "integrators" / "README.md", '"""my_stepper.py', site)
    return site


@pytest.fixture
def installed(site, monkeypatch):
    from reelbench.integrators import registry

    monkeypatch.syspath_prepend(str(site))
    yield site
    registry.unregister(NAME)
    sys.modules.pop("my_stepper", None)


def _benchmark(site, *args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(site)]))
    return subprocess.run([sys.executable, "-m", "benchmark", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)


def test_defaults_keep_to_the_projects_own_methods(installed):
    from reelbench.benchmark.studies import stability
    from reelbench.benchmark.runs import sweep
    from reelbench.integrators import available, origin, registry

    assert NAME in available()
    assert origin(NAME) == ("my-stepper", "0.1", False)
    assert origin("lgvi").own and origin("rk45").own  # a decorator and one of the project's entry points
    assert origin("lgvi").package == "reelbench"
    assert NAME not in registry.own() and NAME not in sweep.default_names()
    assert NAME not in stability.default_integrators()
    assert NAME in sweep.default_names(plugins=True) and sweep.plugin_names(["lgvi", NAME]) == [NAME]
    assert {t.integrator for t in sweep.build_tasks(["fixed_length"], quick=True)} == set(sweep.default_sweep_names())


def test_a_run_that_would_add_plugin_rows_to_results_is_refused_in_one_line(site):
    for args in (["run", "--with-plugins"], ["run", "--integrators", NAME], ["run", "--quick", "--with-plugins"]):
        proc = _benchmark(site, *args)
        assert proc.returncode == 2, (args, proc.stderr)
        [line] = proc.stderr.strip().splitlines()
        assert line.startswith("error: this run would add the rows of plugin(s) symplectic_euler "
                               "(package my-stepper 0.1) to the committed results/grid/"), line
        assert "--out DIR" in line and "--out results/grid" in line
    both = _benchmark(site, "run", "--with-plugins", "--integrators", "lgvi", "--out", "/tmp/x")
    assert both.returncode == 2 and "--with-plugins" in both.stderr


def test_list_marks_plugins_with_their_package_and_version(site):
    proc = _benchmark(site, "list")
    assert proc.returncode == 0, proc.stderr
    lines = {ln.split()[0]: ln for ln in proc.stdout.splitlines() if ln.startswith("  ")}
    assert lines[NAME].endswith("(plugin, package my-stepper 0.1)"), lines[NAME]
    # a guest joins no sweep unasked: not marked "default" as the project's own methods are
    assert lines[NAME].split()[3] == "plugins" and lines["lgvi"].split()[3] == "default", lines[NAME]
    assert "swept with --with-plugins or when --integrators names it" in proc.stdout
    assert "plugin" not in lines["lgvi"] and "plugin" not in lines["rk45"]


def test_provenance_follows_the_package_and_the_plugins_source(installed, tmp_path):
    from reelbench.benchmark.runs.runner import provenance
    from reelbench.benchmark.core.store import code_version
    from reelbench.models.origin import source_digest, project_origin

    code = code_version()
    own = provenance("lgvi", code)
    assert own == {"package": "reelbench", "package_version": project_origin().version, "code_digest": code}
    guest = provenance(NAME, code)
    assert guest["package"] == "my-stepper" and guest["package_version"] == "0.1"
    assert guest["code_digest"] != code and len(guest["code_digest"]) == 12
    # an edit of the plugin's source changes the digest its rows' resume keys use
    from reelbench.integrators import get_integrator

    cls = type(get_integrator(NAME))
    before = source_digest(cls)
    module = installed / "my_stepper.py"
    module.write_text(module.read_text() + "\n# edited\n")
    try:
        assert source_digest(cls) != before
    finally:
        module.write_text(module.read_text().removesuffix("\n# edited\n"))


def test_with_plugins_or_a_name_brings_them_in(installed, tmp_path, monkeypatch, capsys):
    """What `run` hands its pipeline (stubbed: nothing runs): the plugin joins only when asked."""
    from reelbench.benchmark.cli import main as cli
    from reelbench.benchmark.studies import grid

    seen = []
    monkeypatch.setattr(grid, "run_sweep", lambda request, log: seen.append(request) or 0)
    monkeypatch.chdir(ROOT)
    out = str(tmp_path / "out")
    assert cli.main(["run", "--quick", "--scenes", "fixed_length", "--out", out]) == 0
    assert seen[-1].integrators is None  # the pipeline's default: the project's own methods
    assert cli.main(["run", "--with-plugins", "--quick", "--scenes", "fixed_length", "--out", out]) == 0
    assert NAME in seen[-1].integrators and "lgvi" in seen[-1].integrators
    capsys.readouterr()
    assert cli.main(["run", "--integrators", NAME, "--quick", "--scenes", "fixed_length", "--out", "results/grid"]) == 0
    note = capsys.readouterr().err.strip().splitlines()
    assert note == ["note: results/grid/ gets the rows of plugin(s) symplectic_euler (package my-stepper 0.1), "
                    "as --out asks"], note
