"""The fixed-step contract: the README's plugin, run as an outside package.

The plugin is the ```python block of integrators/README.md that defines a `FixedStepMethod`
(symplectic Euler), written to a temporary package registered through the
`reelbench.integrators` entry-point group: the documentation cannot rot without this failing.
It has no guard code of its own, yet it stops ``diverged`` past its stability limit and
``length_limit`` on a reel scene, and it runs in ``python -m benchmark run`` into runs.csv,
runs.md and the work-precision plot.
"""

import functools
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from reelbench.integrators import ENTRY_POINT_GROUP, Capability, FixedStepMethod, Guards, get_integrator, registry
from reelbench.integrators.base import energy_error_ode
from reelbench.models import build_model, load_scene

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "integrators" / "README.md"
NAME = "symplectic_euler"


def readme_plugin() -> str:
    """The README's complete plugin example (the python block defining a FixedStepMethod)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    return next(b for b in blocks if "(FixedStepMethod)" in b)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A site directory holding the README's plugin as an installed-looking distribution."""
    site = tmp_path_factory.mktemp("site")
    (site / "my_stepper.py").write_text(readme_plugin())
    dist = site / "my_stepper-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-stepper\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n{NAME} = my_stepper:SymplecticEuler\n")
    return site


@pytest.fixture
def plugin(site, monkeypatch):
    monkeypatch.syspath_prepend(str(site))
    yield get_integrator(NAME)
    registry.unregister(NAME)
    sys.modules.pop("my_stepper", None)


def test_the_readme_plugin_is_short_and_has_no_guard_code():
    code = readme_plugin()
    assert len(code.strip().splitlines()) <= 40
    for word in ("isfinite", "Status", "status", "energy", "length", "reason", "Trajectory", "stats", "time"):
        assert word not in code, word


def test_the_plugin_is_found_through_the_entry_point_group(plugin):
    assert isinstance(plugin, FixedStepMethod) and plugin.name == NAME
    assert plugin.has(Capability.FIXED_STEP)  # declared by the base class
    with pytest.raises(ValueError, match="dt"):
        plugin.solve(load_scene("fixed_length", elements=2), t_end=0.1)  # validation is the lifecycle's


def test_past_its_stability_limit_it_stops_diverged_and_keeps_the_trajectory(plugin):
    scene = load_scene("fixed_length", elements=10)
    stable = plugin.solve(scene, t_end=1.0, dt=0.005, save_every=0.02)
    assert stable.ok, stable.reason
    assert stable.stats["steps"] == 200 and stable.stats["rhs_evals"] == 400
    assert stable.stats["wall_time"] >= 0 and stable.stats["compile_time"] >= 0
    # the same run stays within 5 % of the LGVI's at the same dt (a sanity check, not an order: its first
    # order against the reference is measured in the last test)
    lgvi = get_integrator("lgvi").solve(scene, t_end=1.0, dt=0.005, save_every=0.02)
    np.testing.assert_allclose(stable.t, lgvi.t, atol=1e-12)
    assert np.abs(stable.x - lgvi.x).max() < 0.05 * np.abs(lgvi.x).max()

    blown = plugin.solve(scene, t_end=1.0, dt=0.02, save_every=0.02)
    assert blown.status == "diverged" and "energy balance error" in blown.reason, blown.reason
    assert 1 < len(blown) < len(stable)
    for a in (blown.t, blown.x, blown.attitude, blown.velocity, blown.work):
        assert a is None or np.all(np.isfinite(a))
    # what is kept lies on the save grid and within the energy bound
    np.testing.assert_allclose(blown.t, stable.t[: len(blown)], atol=1e-12)
    model, lay = build_model(scene), build_model(scene).layout
    guards = Guards.for_model(model)
    for i in range(len(blown)):
        y = np.zeros(lay.ny)
        y[lay.y_x], y[lay.y_w] = blown.x[i], blown.velocity[i]
        if lay.has_attitude:
            y[lay.y_quat] = blown.attitude[i]
        if lay.has_work:
            y[lay.y_work] = blown.work[i]
        assert float(energy_error_ode(model, y, guards.E0)) <= guards.energy_bound


def test_on_a_reel_scene_it_stops_at_the_length_limit(plugin):
    scene = load_scene("deployment_to_end", elements=4)
    model = build_model(scene)
    traj = plugin.solve(scene, dt=0.002, save_every=0.1)
    assert traj.status == "length_limit", traj.reason
    assert "the string ran out" in traj.reason
    # the scene's own description: the deployed length reaches L - b at t ~ 9.2 s
    assert 8.5 < traj.stats["event_time"] < 10.0
    assert traj.t[-1] <= traj.stats["event_time"]
    ell = model.L - traj.x[:, 0]
    assert np.all(np.isfinite(traj.x)) and np.all(ell < model.L - model.b)


def test_it_runs_in_the_benchmark_into_tables_and_the_work_precision_plot(site, tmp_path, monkeypatch):
    import os

    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(site)]))
    cmd = [sys.executable, "-m", "benchmark", "run", "--scenes", "fixed_length", "--integrators", NAME,
           "--dts", "0.02,0.005,0.0025", "--t-end", "0.4", "--set", "elements=10", "--repeats", "1", "--jobs", "1",
           "--horizon", "0", "--out", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = pd.read_csv(out / "runs.csv")
    mine = runs[runs["integrator"] == NAME].set_index("dt")
    assert set(mine.index) == {0.02, 0.005, 0.0025}
    assert mine.loc[0.02, "status"] == "diverged"
    assert (mine.loc[[0.005, 0.0025], "status"] == "ok").all()
    assert (mine.loc[[0.005, 0.0025], "position_error_final"] > 0).all()
    # first order: halving dt about halves the error
    ratio = mine.loc[0.005, "position_error_final"] / mine.loc[0.0025, "position_error_final"]
    assert 1.5 < ratio < 2.7, ratio
    assert NAME in (out / "runs.md").read_text()
    # whose rows these are: the plugin's package and version, and the code digest its resume key covers
    from reelbench.benchmark.core.store import code_version

    assert set(runs["package"]) == {"my-stepper"} and set(runs["package_version"].astype(str)) == {"0.1"}
    [digest] = set(runs["code_digest"])
    assert len(digest) == 12 and digest != code_version()  # the plugin's source is part of it
    assert (out / "work_precision_fixed_length.png").stat().st_size > 0

    # the work-precision figure has its curve on both cost axes (run time and work count)
    from reelbench.benchmark.figures import plots

    from reelbench.benchmark.figures.styles import style

    seen = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path: seen.append(
        ([t.get_text() for leg in fig.legends for t in leg.get_texts()],
         [{line.get_color() for line in ax.get_lines()} for ax in fig.axes])) or path)
    plots.work_precision(runs, "fixed_length", tmp_path)
    legend, colours = seen[0]
    assert f"{NAME} (fixed dt)" in legend  # one legend for the figure, outside the axes
    assert len(colours) == len(plots.COST_AXES) * len(plots.ERROR_LABELS)
    assert all(style(NAME).color in c for c in colours)  # in every panel, in its own colour


# ------------------------------------------------------------------------------------------
# The second README example: a step returning a StepResult
# ------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def readme_step_result_plugin():
    """The README's example of a step that returns (carry, StepResult) (one class object, so
    that the tests share its compiled loops)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    code = next(b for b in blocks if "StepResult(" in b and "(FixedStepMethod)" in b)
    namespace = {}
    exec(compile(code, "implicit_midpoint.py", "exec"), namespace)
    return namespace["ImplicitMidpoint"]


def test_a_step_returning_a_step_result_counts_its_iterations_and_fails_by_its_code():
    method = readme_step_result_plugin()()
    assert method.name == "implicit_midpoint" and method.implementation == "jax-compiled"
    scene = load_scene("fixed_length", elements=3)
    ok = method.solve(scene, t_end=0.2, dt=0.002, save_every=0.02)
    assert ok.ok, ok.reason
    # the iterations of every step are summed (a few fixed-point iterations per step, converged)
    steps, its = ok.stats["steps"], ok.stats["newton_iterations"]
    assert steps == 100 and 2 * steps <= its <= 50 * steps and 2 <= ok.stats["max_newton_iterations"] <= 50
    # second order, like the LGVI at this step: within 1e-4 m of it
    lgvi = get_integrator("lgvi").solve(scene, t_end=0.2, dt=0.002, save_every=0.02)
    assert np.abs(ok.x - lgvi.x).max() < 1e-4
    # its options reach the traced step as run-time values: a cap of 2 iterations fails at once
    bad = method.solve(scene, t_end=0.2, dt=0.002, save_every=0.02, max_iter=2)
    assert bad.status == "newton_failed" and bad.reason.startswith("step 1 ")
    assert bad.stats["steps"] == 0 and len(bad.t) == 1 and bad.stats["compile_time"] < ok.stats["compile_time"] / 2
    with pytest.raises(ValueError, match="unknown option"):
        method.solve(scene, t_end=0.2, dt=0.002, bogus=1)


def test_both_step_forms_run_on_the_same_lifecycle(plugin):
    """The old-style step (a carry) reports no iteration counts; the StepResult one does."""
    scene = load_scene("fixed_length", elements=3)
    plain = plugin.solve(scene, t_end=0.02, dt=0.002)
    counted = readme_step_result_plugin()().solve(scene, t_end=0.02, dt=0.002)
    assert "newton_iterations" not in plain.stats and "newton_iterations" in counted.stats
    assert set(plain.stats) - {"rhs_evals"} == set(counted.stats) - {"newton_iterations", "max_newton_iterations"}
