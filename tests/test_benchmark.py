"""The benchmark runner on a tiny sweep: rows, statuses, atomic writes, cached references."""

import numpy as np
import pytest

from reelbench.benchmark.runs import runner
from reelbench.benchmark.runs import sweep
from reelbench.benchmark.runs.metrics import ACCURACY, COLUMNS, fastest_at, observed_orders
from reelbench.benchmark.core.reference import get_reference, reference_path
from reelbench.integrators import Capability, Integrator, Status, Trajectory, get_integrator, register
from reelbench.integrators import registry
from reelbench.models import load_scene
from reelbench.models.io import atomic_path, atomic_write_text

pytest.importorskip("reelbench.integrators.scipy_ivp")


@pytest.fixture
def flaky_integrators():
    """Two test integrators: one that raises, one that reports divergence."""

    @register
    class Raises(Integrator):
        name = "test_raises"
        capabilities = frozenset({Capability.FIXED_STEP})

        def solve(self, scene, t_end=None, **kw):
            raise RuntimeError("boom")

    @register
    class Diverges(Integrator):
        name = "test_diverges"
        capabilities = frozenset({Capability.FIXED_STEP})

        def solve(self, scene, t_end=None, *, dt=None, **kw):
            inner = get_integrator("lgvi").solve(scene, t_end=2 * dt, dt=dt, save_every=dt)
            inner.status, inner.reason = Status.DIVERGED.value, "energy grew beyond bound at t=0.01"
            return inner

    yield
    registry.unregister("test_raises")
    registry.unregister("test_diverges")


def test_tiny_sweep_rows_statuses_and_orders(tmp_path, flaky_integrators):
    tasks = sweep.build_tasks(["fixed_length"], ["lgvi", "rk45", "test_raises", "test_diverges"],
                              dts=[0.01, 0.005], rtols=[1e-5, 1e-7], t_end=0.2, overrides={"elements": 2})
    assert len(tasks) == 2 + 2 + 2 + 2
    written = []
    runs = runner.execute(tasks, executor="serial", repeats=1, cache_dir=str(tmp_path / "cache"),
                          on_row=lambda rows: written.append(len(rows)), log=lambda s: None)
    assert written == list(range(1, len(tasks) + 1))  # partial results after every run
    assert list(runs.columns[: len(COLUMNS)]) == COLUMNS
    ok = runs[runs["status"] == "ok"]
    assert set(ok["integrator"]) == {"lgvi", "rk45"} and len(ok) == 4
    for col in ACCURACY + ["run_time", "steps", "run_time_low", "run_time_high", "load_avg", "flops"]:
        assert np.all(np.isfinite(ok[col].astype(float))), col
    assert (ok["flops"] > 0).all() and ok["flops_note"].str.len().gt(0).all()
    # the timing spread: the median of as many solves as fit in the budget, between the fastest and the slowest
    assert (ok["run_time_low"] <= ok["run_time"]).all() and (ok["run_time"] <= ok["run_time_high"]).all()
    assert (ok["timing_repeats"] >= 1).all() and (ok["timing_repeats"] <= sweep.MAX_REPEATS).all()
    # per right-hand-side evaluation where they are counted (rk45); the LGVI evaluates none
    rk = ok[ok["integrator"] == "rk45"]
    np.testing.assert_allclose(rk["us_per_eval"], 1e6 * rk["run_time"] / rk["rhs_evals"])
    assert ok.loc[ok["integrator"] == "lgvi", "us_per_eval"].isna().all()
    assert (ok["implementation"] == "jax-compiled").sum() == 2 and (ok["implementation"] == "scipy-python").sum() == 2
    assert runs["row_digest"].notna().all() and runs["scene_key"].notna().all()
    assert (ok["position_error_final"] < 1e-2).all()
    raised = runs[runs["integrator"] == "test_raises"]
    assert (raised["status"] == "error").all() and raised["reason"].str.contains("boom").all()
    div = runs[runs["integrator"] == "test_diverges"]
    assert (div["status"] == "diverged").all() and div[ACCURACY].isna().all().all()
    orders = observed_orders(runs)
    lg = orders[(orders["integrator"] == "lgvi")]["observed_order"].iloc[0]
    assert 1.5 < lg < 2.6, orders
    table = fastest_at(runs, "position_error_final", 1.0)
    assert set(table["integrator"]) == {"lgvi", "rk45"} and table["factor"].min() == 1.0


def test_bad_sweep_input_is_refused_before_work():
    with pytest.raises(ValueError, match="dt = -0.003"):
        sweep.build_tasks(["fixed_length"], ["lgvi"], dts=[-0.003])
    assert sweep.build_tasks(["fixed_length"], ["lgvi"], dts=[0.003])[0].dt == 0.003  # any step size
    with pytest.raises(ValueError, match="rtol"):
        sweep.build_tasks(["fixed_length"], ["rk45"], rtols=[2.0])
    with pytest.raises(ValueError, match="unknown integrator"):
        sweep.build_tasks(["fixed_length"], ["lgvy"])


def test_reference_is_cached_and_reused(tmp_path, monkeypatch):
    scene = load_scene("fixed_length", elements=2)
    ref = get_reference(scene, 0.1, 0.02, tmp_path)
    path = reference_path(scene, 0.1, 0.02, tmp_path)
    assert path.exists() and ref.ok
    # a second call must not integrate again
    monkeypatch.setattr("reelbench.benchmark.core.reference.get_integrator", lambda name: pytest.fail("recomputed"))
    again = get_reference(scene, 0.1, 0.02, tmp_path)
    np.testing.assert_array_equal(again.x, ref.x)
    # a different scene gets a different key
    assert reference_path(scene.with_(axial_stiffness=300.0), 0.1, 0.02, tmp_path) != path


def test_atomic_writes_leave_old_file_on_failure(tmp_path):
    target = tmp_path / "runs.csv"
    atomic_write_text(target, "old\n")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["runs.csv"]


def test_trajectory_save_load_round_trip(tmp_path):
    scene = load_scene("fixed_length", elements=2)
    traj = get_integrator("lgvi").solve(scene, t_end=0.05, dt=0.01)
    traj.save(tmp_path / "t.npz")
    back = Trajectory.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(back.x, traj.x)
    assert back.status == traj.status and back.integrator == "lgvi"


def test_cli_refuses_bad_input_before_work(tmp_path, capsys):
    from reelbench.benchmark.cli.main import main

    assert main(["run", "--dts", "20", "--out", str(tmp_path)]) == 2
    assert "dt = 20 s is longer than the run" in capsys.readouterr().err
    assert main(["run", "--set", "elements=0", "--out", str(tmp_path)]) == 2
    assert "string.elements" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing was written
    assert main(["list"]) == 0
    assert "lgvi" in capsys.readouterr().out


def test_atomic_writes_keep_the_umask_mode(tmp_path):
    import os

    target = tmp_path / "table.csv"
    atomic_write_text(target, "a\n")
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(target).st_mode & 0o777 == 0o666 & ~umask


def test_reel_reversal_command_prints_errors_falling_with_the_step(tmp_path, capsys):
    """The reel-reversal study on the engine, against the cached reference: one row per step
    size, each error smaller at the smaller step, and an order between successive steps."""
    from reelbench.benchmark.cli.main import main

    args = ["reel-reversal", "--integrators", "lgvi_sym", "--elements", "2", "--t-end", "0.16", "--jobs", "0",
            "--cache-dir", str(tmp_path), "--out", str(tmp_path / "out")]
    assert main(args) == 0
    rows = [line.split("|")[1:-1] for line in capsys.readouterr().out.splitlines() if line.startswith("| lgvi_sym |")]
    assert [float(r[1]) for r in rows] == [4, 2, 1, 0.5]  # h in ms
    errors = np.array([[float(v) for v in r[2:5]] for r in rows])
    assert np.all(errors[1:] < errors[:-1]), errors
    orders = [[float(v) for v in r[5].split("/")] for r in rows[1:]]
    assert len(orders) == 3 and all(len(o) == 3 for o in orders)
    assert list(tmp_path.glob("reference-reel_reversal-*.npz"))  # the reference path's cache


def test_speed_command_writes_its_tables_under_the_report_header(tmp_path, capsys):
    from reelbench.benchmark.cli.main import main

    out = tmp_path / "speed.md"
    assert main(["speed", "--integrators", "lgvi,tsit5", "--scenes", "fixed_length", "--elements", "2", "--steps", "20",
                 "--repeats", "1", "--rhs", "closed_form", "--out", str(out)]) == 0
    text = out.read_text()
    assert text == capsys.readouterr().out.rstrip("\n") + "\n"  # echoed as written
    assert "Generated by `python -m benchmark speed --integrators lgvi" in text and "load average" in text
    assert "| lgvi | fixed_length | 2 |" in text and "| fixed_length | 2 | closed_form |" in text
    assert "| µs/evaluation | flops/step |" in text
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]]
            for line in text.splitlines() if line.startswith(("| lgvi | fixed_length | 2 |", "| tsit5 | fixed_length | 2 |"))}
    # the LGVI evaluates no right-hand side (said, not blank); both have flops per step
    assert rows["lgvi"][6].startswith("— (no RHS evaluations") and float(rows["lgvi"][7]) > 0
    assert float(rows["tsit5"][6]) > 0 and float(rows["tsit5"][7]) > 0


def test_a_method_s_own_sweep_tolerances_and_their_overrides():
    """`SWEEP_RTOLS` (rk45 and its projected variant stop at 1e-8) applies to the full default
    sweep only; --rtols and --quick override it, and the other adaptive methods keep the shared ones."""
    from reelbench.benchmark.runs.sweep import FULL_RTOLS, QUICK_RTOLS, build_tasks

    def rtols(tasks, name):
        return sorted({t.rtol for t in tasks if t.integrator == name and t.rtol is not None})

    full = build_tasks(scenes=("fixed_length",), integrators=["rk45", "rk45_projected", "dopri5"])
    assert rtols(full, "rk45") == rtols(full, "rk45_projected") == [1e-8, 1e-6, 1e-4]
    assert rtols(full, "dopri5") == sorted(FULL_RTOLS)
    assert rtols(build_tasks(scenes=("fixed_length",), integrators=["rk45"], quick=True), "rk45") == sorted(QUICK_RTOLS)
    assert rtols(build_tasks(scenes=("fixed_length",), integrators=["rk45"], rtols=[1e-10]), "rk45") == [1e-10]


def test_every_fixed_step_method_gets_the_one_step_grid():
    """Like with like: the full default sweep gives every fixed-step method the same step sizes
    (the symmetric LGVIs had their own, down to 78 µs, while Suzuki started at 10 ms); --dts
    replaces the grid for all of them at once."""
    from reelbench.benchmark.runs.sweep import FULL_DTS, SAVE_EVERY, build_tasks
    from reelbench.integrators import Capability, get_integrator

    tasks = build_tasks(scenes=("fixed_length",))
    grids = {}
    for t in tasks:
        if t.dt is not None:
            grids.setdefault(t.integrator, []).append(t.dt)
    fixed = {n for n in {t.integrator for t in tasks} if get_integrator(n).has(Capability.FIXED_STEP)}
    assert set(grids) == fixed and {"lgvi", "lgvi_sym", "lgvi_suzuki4", "lie_rk4", "tsit5"} <= fixed
    assert all(sorted(g) == sorted(FULL_DTS) for g in grids.values())
    assert max(FULL_DTS) == SAVE_EVERY and min(FULL_DTS) == SAVE_EVERY / 2 ** 8
    named = build_tasks(scenes=("fixed_length",), integrators=["lgvi_sym", "lie_rk4"], dts=[0.005])
    assert sorted(t.dt for t in named) == [0.005, 0.005]


def test_extended_sweep_methods_run_only_when_named():
    """A method of the sweep's ``EXTENDED_METHODS`` is left out of `run` without --integrators and
    runs when named; every other registered method is in the default sweep."""
    from reelbench.benchmark.runs.sweep import EXTENDED_METHODS, build_tasks, default_names

    default = {t.integrator for t in build_tasks(scenes=("fixed_length",))}
    extended = {n for n in default_names() if n in EXTENDED_METHODS}
    assert {"rk45_projected", "dopri5", "dopri8", "kvaerno5", "crouch_grossman3"} <= extended
    assert default == set(default_names()) - extended and {"lgvi", "lie_rk4", "rattle", "rk45", "radau"} <= default
    named = {t.integrator for t in build_tasks(scenes=("fixed_length",), integrators=sorted(extended))}
    assert named == extended
