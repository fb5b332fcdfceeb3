"""The search for the cheapest setting meeting a target (`benchmark.answer.search`): on synthetic curves
with a known crossing and a known stability cliff, both found within 10 %; never extrapolated;
budget, range and non-monotone (adaptive) cases; and one real method on one scene."""

import math

import numpy as np
import pytest

from reelbench.benchmark.answer.search import RESOLUTION, search


def fixed_step(C=1e3, order=4, cliff=math.inf, calls=None):
    """A fixed-step method: error C dt^order, cost 1 / dt (steps), diverged beyond ``cliff``."""
    def run(dt):
        if calls is not None:
            calls.append(dt)
        if dt > cliff:
            return "diverged", math.nan, math.nan
        return "ok", C * dt ** order, 1.0 / dt
    return run


def crossing(C, order, target):
    return (target / C) ** (1.0 / order)


@pytest.mark.parametrize("start", [1e-4, 0.003, 0.02, 0.5])
def test_a_known_crossing_is_found_within_10_percent(start):
    target = 1e-6
    star = crossing(1e3, 4, target)  # 5.6e-3
    calls = []
    f = search(fixed_step(calls=calls), target, start, lowest=1e-6, highest=1.0)
    assert f.bound == "target"
    assert star / (1 + RESOLUTION) <= f.setting <= star  # meets the target, within 10 % of the crossing
    assert f.setting_low == f.setting < star < f.setting_high <= f.setting * (1 + RESOLUTION) * (1 + 1e-12)
    assert f.error <= target and f.cost == pytest.approx(1.0 / f.setting)
    assert f.spread <= RESOLUTION
    assert f.setting in calls  # never extrapolated: the answer was run
    assert f.runs <= 16


@pytest.mark.parametrize("start", [1e-4, 0.004, 0.05])
def test_a_known_stability_cliff_is_found_within_10_percent(start):
    target, cliff = 1e-4, 0.0095  # the crossing (0.0178) lies beyond the cliff
    assert crossing(1e3, 4, target) > cliff
    f = search(fixed_step(cliff=cliff), target, start, lowest=1e-6, highest=1.0)
    assert f.bound == "stability" and f.high_status == "diverged"
    assert cliff / (1 + RESOLUTION) <= f.setting <= cliff < f.setting_high <= f.setting * (1 + RESOLUTION) * (1 + 1e-12)


def test_the_answer_is_a_measured_point_never_an_extrapolation():
    """A curve whose error jumps at one setting: the answer is the last measured setting that
    met the target, never a guess beyond it."""
    target = 1e-3

    def run(dt):
        return "ok", (1e-4 if dt <= 0.01 else 1.0), 1.0 / dt

    f = search(run, target, 0.001, lowest=1e-5, highest=1.0)
    assert f.setting <= 0.01 and f.setting_high > 0.01 and f.error == 1e-4
    assert any(p.setting == f.setting and p.meets(target) for p in f.points)


def test_the_budget_ends_the_search_and_the_row_says_so():
    f = search(fixed_step(), 1e-6, 1e-5, lowest=1e-8, highest=1.0, max_runs=3)
    assert f.runs == 3 and f.bound == "budget"
    assert f.setting == pytest.approx(4e-5) and math.isnan(f.setting_high)  # the setting reached, still meeting it
    f = search(fixed_step(), 1e-12, 0.1, lowest=1e-8, highest=1.0, max_runs=4)
    assert f.bound == "budget" and math.isnan(f.setting) and f.setting_high == pytest.approx(0.1 / 8)


def test_a_run_stopped_by_its_own_budget_ends_the_finer_search():
    calls = []

    def run(dt):
        calls.append(dt)
        return ("time_limit", float("nan"), float("nan")) if dt < 1e-3 else ("ok", 1.0, 1 / dt)

    f = search(run, 1e-3, 0.01, lowest=1e-8, highest=1.0)
    assert f.bound == "budget" and min(calls) < 1e-3 and sum(dt < 1e-3 for dt in calls) == 1


def test_a_target_never_met_is_not_reached_and_the_coarsest_setting_is_the_largest():
    f = search(lambda dt: ("ok", 1.0, 1 / dt), 1e-3, 0.01, lowest=1e-3, highest=1.0)
    assert f.bound == "not reached" and math.isnan(f.setting)
    f = search(fixed_step(C=1e-9), 1e-3, 0.01, lowest=1e-3, highest=0.5)
    # the coarsest lattice setting within the range (start · 2^(k/8) <= 0.5)
    assert f.bound == "largest setting" and 0.5 / 2 ** 0.125 < f.setting <= 0.5 and math.isnan(f.setting_high)


def test_an_adaptive_non_monotone_curve_gives_the_cheapest_setting_that_stands():
    """error(tol) = 0.1 tol: meets 1e-6 at tol <= 1e-5, misses above, and meets again on a bump
    near tol = 3e-5 (a lucky step sequence); cost falls with tol. The bump's settings meet the
    target but the settings just finer do not, so none of them stands: the answer is the cheapest
    setting whose three finer neighbours meet it too, and the row names the lucky one above it."""
    def run(tol):
        lucky = 2.5e-5 <= tol <= 4e-5
        err = 5e-7 if lucky else (0.1 * tol if tol > 1e-7 else 1e-8)
        return "ok", err, tol ** -0.2

    f = search(run, 1e-6, 1e-4, lowest=1e-14, highest=0.1, factor=10.0)
    assert f.confirmed and f.setting <= 1e-5 * (1 + 1e-9)
    assert f.setting * 10 ** 0.25 > 1e-5  # within a lattice step of the crossing (1e-5 itself misses by an ulp)
    standing = [p for p in f.points if p.meets(1e-6) and p.setting <= 1e-5 * (1 + 1e-9)]
    assert f.cost == min(p.cost for p in standing)
    settings = sorted(p.setting for p in f.points)
    i = settings.index(f.setting)  # its measured neighbours on either side
    assert f.setting_finer == settings[i - 1] and f.setting_high == settings[i + 1]
    lucky = [p for p in f.points if p.meets(1e-6) and p.setting > 1.1e-5]
    if lucky:  # the bisection found the bump: it is named, never the answer
        assert 2.5e-5 <= f.erratic_above <= 4e-5 and f.non_monotone
    f = search(run, 1e-6, 3e-5, lowest=1e-14, highest=0.1, factor=10.0)  # start on the bump
    assert f.confirmed and f.setting <= 1e-5 and f.erratic_above == 3e-5 and f.non_monotone


def _erratic_dop853(calls=None):
    """The deployment case of DOP853 at N = 10, position <= 1e-6 (measured on the 1/8-decade grid):
    rtol 1e-3 passes (6.0e-7 m) but 1.33e-3, 1.78e-3 and 5.6e-4 fail; every rtol <= 4.2e-4 passes.
    The step is held by stability, so the cost barely moves."""
    def run(rtol):
        if calls is not None:
            calls.append(rtol)
        k = round(math.log10(rtol) * 8)  # the 1/8-decade lattice index (1e-3 -> -24)
        if k >= -23 and k != -24:  # 7.5e-4 and coarser, except the lucky 1e-3
            err = 1.05e-6 if k in (-23, -22, -21, -20) else 3.1e-6
        elif k == -24:
            err = 6.0e-7
        elif k == -26:  # 5.6e-4
            err = 1.02e-6
        elif k == -25:  # 7.5e-4
            err = 8e-7
        else:  # <= 4.2e-4
            err = 2e-7 * 10 ** ((k + 27) / 8)
        return "ok", err, 7787.0 + 10.0 * (-k)
    return run


def test_a_lucky_setting_is_not_published_the_one_that_stands_is():
    calls = []
    f = search(_erratic_dop853(calls), 1e-6, 1e-6, lowest=1e-13, highest=0.1, factor=10.0)
    assert f.confirmed and f.bound == "target"
    assert f.setting <= 4.3e-4, f  # below the erratic region: rtol <= 4.2e-4 passes everywhere
    assert f.setting == pytest.approx(10 ** (-27 / 8))  # the coarsest setting that stands
    for j in (1, 2, 3):  # its three finer neighbours were run and met the target
        assert any(p.setting == pytest.approx(f.setting / 10 ** (j / 8)) and p.meets(1e-6) for p in f.points)
    assert f.erratic_above == pytest.approx(1e-3) and f.non_monotone
    assert f.runs <= 24


def test_a_monotone_answer_is_confirmed_by_its_three_finer_neighbours():
    f = search(fixed_step(), 1e-6, 0.005, lowest=1e-6, highest=1.0)
    assert f.confirmed and math.isnan(f.erratic_above) and not f.non_monotone
    finer = sorted((p.setting for p in f.points if p.setting < f.setting), reverse=True)[:3]
    assert finer == pytest.approx([f.setting / 2 ** (j / 8) for j in (1, 2, 3)])


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="lowest <= start <= highest"):
        search(fixed_step(), 1e-6, 2.0, lowest=1e-6, highest=1.0)
    with pytest.raises(ValueError, match="target"):
        search(fixed_step(), -1.0, 0.1, lowest=1e-6, highest=1.0)


def test_a_real_method_and_scene():
    """lie_rk4 on a two-element fixed_length over 0.2 s, energy error <= 1e-7: the answer meets
    the target, the bracket's coarser end (within 10 % in steps) does not, with the flop-free
    cost of steps."""
    from reelbench.benchmark.runs.metrics import run_metrics
    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    scene = load_scene("fixed_length", elements=2)
    integ = get_integrator("lie_rk4")

    def run(dt):
        traj = integ.solve(scene, t_end=0.2, dt=dt, save_every=0.02)
        return traj.status, run_metrics(scene, traj, None, 0.02)["energy_error"], float(traj.stats["steps"])

    f = search(run, 1e-7, 0.005, lowest=1e-5, highest=0.2)
    assert f.bound in ("target", "stability"), f
    status, err, steps = run(f.setting)
    assert status == "ok" and err <= 1e-7
    st, err_high, steps_high = run(f.setting_high)
    assert not (st == "ok" and err_high <= 1e-7)
    assert steps <= np.ceil(steps_high * 1.1) + 1
