"""Any step size: a fixed step saves at its step points nearest the save times, its last step is
shortened to land on t_end, a new step size compiles nothing, and the reference is read at the
times a run saved by its dense output."""

import numpy as np
import pytest

from reelbench.benchmark.runs import sweep
from reelbench.benchmark.runs.metrics import run_metrics
from reelbench.benchmark.core.reference import get_reference, reference_at
from reelbench.integrators import get_integrator
from reelbench.integrators.base import fixed_step_grid, save_times
from reelbench.models import load_scene


@pytest.mark.parametrize("t_end, dt", [(1.0, 0.003), (1.0, 0.005), (10.0, 0.00889), (1.0, 0.3), (0.2, 0.2)])
def test_the_grid_ends_at_t_end_for_any_step(t_end, dt):
    n, idx = fixed_step_grid(t_end, dt, 0.02)
    assert (n - 1) * dt < t_end <= n * dt * (1 + 1e-12)  # n steps reach t_end, n - 1 do not
    assert idx[0] == 0 and idx[-1] == n and np.all(np.diff(idx) > 0)
    t = save_times(t_end, 0.02, dt)
    assert t[-1] == t_end
    # every saved time but the last is a step point within dt / 2 of a save time
    grid = save_times(t_end, 0.02)
    assert np.all(np.min(np.abs(t[:-1, None] - grid[None, :]), axis=1) <= dt / 2 + 1e-12)


def test_a_dividing_step_saves_on_the_save_grid():
    n, idx = fixed_step_grid(10.0, 0.005, 0.02)
    assert n == 2000 and np.array_equal(idx, np.arange(0, 2001, 4))


def test_any_step_size_is_accepted_by_the_sweep():
    sweep.check_settings([0.003, 0.00889, 0.04])
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="allowed: a finite number > 0"):
            sweep.check_settings([bad])


@pytest.mark.parametrize("name", ["lie_rk4", "tsit5"])  # the lifecycle's loop, diffrax's constant step
def test_a_run_at_any_step_ends_at_t_end_and_a_new_step_compiles_nothing(name):
    scene = load_scene("fixed_length", elements=2)
    integ = get_integrator(name)
    first = integ.solve(scene, t_end=0.1, dt=0.005, save_every=0.02)
    for dt in (0.003, 0.007, 0.0123, 0.03):  # 0.03: longer than the save interval
        traj = integ.solve(scene, t_end=0.1, dt=dt, save_every=0.02)
        assert traj.ok and traj.t[-1] == 0.1, (dt, traj.t[-1])
        assert np.all(np.diff(traj.t) > 0)
        assert traj.stats["steps"] == int(np.ceil(0.1 / dt))
        assert traj.stats["compile_time"] < 0.05 * first.stats["compile_time"], dt  # the same compiled loop


def test_the_shortened_last_step_is_a_step_of_the_method():
    """dt = 0.03 over 0.1 s: three steps of 0.03 and one of 0.01 end where a dt = 0.01 run that
    takes the same last step from the same state would (RK4 at dt^4 accuracy: close to the
    dt = 0.001 run, far closer than the error of stopping at 0.09)."""
    scene = load_scene("fixed_length", elements=2)
    integ = get_integrator("lie_rk4")
    coarse = integ.solve(scene, t_end=0.1, dt=0.03, save_every=0.02)
    fine = integ.solve(scene, t_end=0.1, dt=0.001, save_every=0.02)
    at_09 = integ.solve(scene, t_end=0.09, dt=0.001, save_every=0.02)
    err = np.abs(coarse.x[-1] - fine.x[-1]).max()
    assert err < 0.1 * np.abs(at_09.x[-1] - fine.x[-1]).max()


def test_the_reference_is_read_at_the_times_a_run_saved(tmp_path):
    """Its dense output at the saved times of one save interval agrees with a reference solved
    to save at exactly those times (both DOP853 at rtol 1e-12), and a run's position error
    comes from every one of its saved times."""
    scene = load_scene("fixed_length", elements=2)
    ref = get_reference(scene, 0.2, 0.02, tmp_path, log=None)
    other = get_reference(scene, 0.2, 0.0125, tmp_path, log=None)  # other saved times
    at = reference_at(scene, ref, other.t)
    assert np.abs(at.x[:, -3:] - other.x[:, -3:]).max() < 1e-9  # the body's coordinates: what is compared
    assert np.abs(at.attitude - other.attitude).max() < 1e-9
    again = get_reference(scene, 0.2, 0.02, tmp_path, log=None)  # from the cache, dense output included
    assert np.array_equal(again.dense(other.t), ref.dense(other.t))
    with pytest.raises(ValueError, match="never extrapolated"):
        ref.dense([0.25])
    traj = get_integrator("lie_rk4").solve(scene, t_end=0.2, dt=0.003, save_every=0.02)
    m = run_metrics(scene, traj, ref, 0.02)
    assert np.isfinite(m["position_error_final"]) and m["position_error_final"] <= m["position_error_max"]


def test_simulate_at_a_step_that_does_not_divide_the_save_interval_ends_at_t_end(tmp_path):
    """`simulate --dt 0.003 --t-end 1` saved every 0.021 s and ended at t = 0.999 s: now its
    saved times are the step points nearest every 0.02 s and its last one is t_end."""
    from reelbench.benchmark.cli.main import main
    from reelbench.integrators import Trajectory

    out = tmp_path / "t.npz"
    assert main(["simulate", "fixed_length", "--integrators", "lie_rk4", "--dt", "0.003", "--t-end", "0.5",
                 "--set", "elements=2", "--out", str(out)]) == 0
    traj = Trajectory.load(out)
    assert traj.t[-1] == 0.5 and len(traj.t) == 26
    assert np.all(np.abs(traj.t[:-1] - np.round(traj.t[:-1] / 0.02) * 0.02) <= 0.0015 + 1e-12)
