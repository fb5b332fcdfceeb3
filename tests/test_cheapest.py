"""benchmark.cheapest: the cost at a target read off each method's own curve, with its interval,
and verdicts that say "tie" where the intervals overlap."""

import math
import re

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmark.cheapest import (COLUMNS, WALL_RESOLUTION, WORK_RESOLUTION, cheapest, cost_on_curve, failure_causes,
                                failure_summary, summary_lines)
from benchmark.metrics import ACCURACY

#: Timing noise measured on the shared 2-core machine (load 2.2–2.9): 30 interleaved solves each
#: of lgvi dt = 5 ms, tsit5 rtol 1e-6 and dop853 rtol 1e-6 on fixed_length, each solve's
#: wall time divided by the fastest of its 30 (so every factor is >= 1).
MEASURED_NOISE = np.array([
    2.69, 1.63, 1.18, 1.95, 2.07, 1.01, 1.36, 1.54, 1.55, 1.01, 1.63, 1.76, 1.08, 1.23, 1.71,
    1.0, 1.58, 1.06, 1.04, 1.75, 1.06, 1.52, 1.25, 1.61, 1.65, 1.24, 1.33, 1.19, 1.3, 1.48,
    2.04, 2.12, 1.29, 1.92, 2.24, 1.47, 1.21, 1.48, 1.63, 1.21, 1.28, 1.25, 1.23, 1.42, 1.59,
    1.14, 1.52, 1.23, 1.13, 1.24, 1.22, 1.4, 1.23, 1.54, 1.41, 1.65, 1.0, 1.32, 1.57, 1.37,
    1.24, 1.32, 1.24, 1.39, 2.14, 1.68, 2.01, 2.26, 1.47, 1.59, 1.32, 1.0, 1.19, 1.19, 1.44,
    1.17, 1.29, 1.22, 1.18, 1.08, 1.3, 1.07, 1.08, 1.22, 1.18, 1.14, 1.11, 1.13, 1.16, 1.17])


def row(integrator, setting, *, status="ok", error=1e-6, time=1.0, low=None, high=None, work=1000.0, scene="s",
        **extra):
    axis, value = setting.split("=")
    return {"scene": scene, "integrator": integrator, "setting": setting,
            "dt": float(value) if axis == "dt" else np.nan, "rtol": float(value) if axis == "rtol" else np.nan,
            "t_end": 1.0, "status": status, "energy_error": error if status == "ok" else np.nan,
            "run_time": time, "run_time_low": time if low is None else low, "run_time_high": time if high is None else high,
            "work_evals": work, **extra}


def table(*rows):
    return pd.DataFrame(list(rows))


def one(t, integrator, kind="wall"):
    r = t[(t["integrator"] == integrator) & (t["cost_kind"] == kind)]
    assert len(r) == 1
    return r.iloc[0]


# ---- the curve ----------------------------------------------------------------------------
def test_a_power_law_curve_is_interpolated_exactly_between_the_bracketing_settings():
    # error = 1e-2 * (cost / 100)^-2: the log-log line through every point; target between points 2 and 3
    costs = np.array([100.0, 200.0, 400.0, 800.0])
    errors = 1e-2 * (costs / 100) ** -2
    cost, low, high, i, j = cost_on_curve(errors, costs, costs * 0.9, costs * 1.2, 1e-3)
    assert (i, j) == (1, 2)
    assert cost == pytest.approx(100 * math.sqrt(10), rel=1e-12)
    assert low == pytest.approx(0.9 * cost, rel=1e-12) and high == pytest.approx(1.2 * cost, rel=1e-12)


def test_nothing_is_extrapolated():
    costs, errors = [1.0, 2.0, 4.0], [1e-3, 1e-4, 1e-5]
    assert cost_on_curve(errors, costs, costs, costs, 1e-6) is None  # finer than the finest: not reached
    # looser than the coarsest: the coarsest setting's own cost, not a cheaper extrapolated one
    assert cost_on_curve(errors, costs, costs, costs, 1e-2) == (1.0, 1.0, 1.0, 0, 0)
    assert cost_on_curve(errors, costs, costs, costs, 1e-4)[:1] == (2.0,)  # a point on the target: its cost


def test_a_non_monotone_curve_counts_its_cheapest_crossing():
    # the error crosses 1e-4 going down twice (between settings 0-1 and 2-3); the first is cheaper
    costs, errors = [1.0, 2.0, 4.0, 8.0], [1e-3, 1e-5, 1e-3, 1e-5]
    cost, *_, i, j = cost_on_curve(errors, costs, costs, costs, 1e-4)
    assert (i, j) == (0, 1) and cost == pytest.approx(math.sqrt(2))


def test_failed_runs_are_no_points_of_the_curve():
    t = cheapest(table(row("a", "dt=0.04", error=1e-2, time=1.0),
                       row("a", "dt=0.02", status="newton_failed", time=0.01),
                       row("a", "dt=0.01", error=1e-4, time=4.0)), [("energy_error", 1e-3)])
    a = one(t, "a")
    assert a["bracket"] == "dt=0.04 .. dt=0.01" and a["cost"] == pytest.approx(2.0)


def test_an_inaccurate_run_is_no_point_of_the_curve_and_no_cost_is_read_across_it():
    # the cliff: at dt = 0.02 the run finished but is no solution (its error, 1.2, was taken
    # away with its status); a curve through it would put the crossing at the cheap end
    runs = table(row("a", "dt=0.02", status="inaccurate", time=1.0), row("a", "dt=0.01", error=1e-6, time=4.0),
                 row("b", "dt=0.04", error=1e-2, time=1.0), row("b", "dt=0.02", status="inaccurate", time=2.0),
                 row("b", "dt=0.01", error=1e-6, time=4.0))
    t = cheapest(runs, [("energy_error", 1e-4)], cost_kinds=["wall"])
    a, b = one(t, "a"), one(t, "b")
    assert a["cost"] == 4.0 and a["bracket"] == "dt=0.01" and a["bound"] == "cliff"
    assert "dt=0.02 inaccurate" in a["note"]
    assert b["bracket"] == "dt=0.04 .. dt=0.01" and b["bound"] == "accuracy"  # between two solutions
    assert "bounded by a cliff (the next coarser setting is no longer a solution)" in summary_lines(t)[0]


def test_inaccurate_runs_are_an_expected_cause_of_their_own():
    runs = table(row("a", "dt=0.02", status="inaccurate"), row("a", "dt=0.01"))
    assert failure_causes(runs)["cause"].tolist() == ["inaccurate"]
    assert failure_summary(runs) == ("1 of 2 runs not ok, all expected: 1 finished with an error beyond a sanity "
                                     "bound (no longer a solution) (inaccurate 1).")


def test_the_coarsest_finished_setting_meeting_the_target_says_what_failed_above_it():
    t = cheapest(table(row("a", "dt=0.02", status="diverged"), row("a", "dt=0.01", error=1e-6, time=3.0)),
                 [("energy_error", 1e-4)])
    a = one(t, "a")
    assert a["cost"] == 3.0 and a["bracket"] == "dt=0.01"
    assert "coarsest finished setting" in a["note"] and "dt=0.02 diverged" in a["note"]


def test_every_method_of_a_scene_gets_a_row_and_why_it_has_no_cost():
    t = cheapest(table(row("a", "dt=0.01", error=1e-6),
                       row("never", "dt=0.01", status="diverged"), row("never", "dt=0.005", status="diverged"),
                       row("coarse", "rtol=1e-3", error=1e-2), row("coarse", "rtol=1e-4", error=1e-3),
                       row("uncounted", "rtol=1e-3", error=1e-6, work=np.nan)),
                 [("energy_error", 1e-4)])
    assert len(t) == 8 and list(t.columns) == COLUMNS
    never, coarse = one(t, "never", "work"), one(t, "coarse")
    assert never["verdict"] == "not reached" and never["note"] == "no finished run (2 diverged)"
    assert coarse["verdict"] == "not reached" and "0.001 (at rtol=1e-4)" in coarse["note"]
    assert one(t, "uncounted", "work")["verdict"] == "not measured"
    assert one(t, "uncounted", "wall")["verdict"] == "tie"  # it has a wall time, equal to a's


def test_work_is_flops_when_the_table_has_them():
    t = cheapest(table(row("a", "dt=0.01", work=10.0, flops=5e6), row("b", "dt=0.01", work=20.0, flops=1e6)),
                 [("energy_error", 1e-4)], cost_kinds=["work"])
    assert set(t["cost_column"]) == {"flops"}
    assert one(t, "b", "work")["verdict"] == "winner" and one(t, "b", "work")["cost"] == 1e6


def test_a_method_with_a_fixed_step_and_an_adaptive_sweep_is_two_entries_ranked_apart():
    t = cheapest(table(row("m", "dt=0.01", time=3.0), row("m", "rtol=1e-4", time=2.0), row("o", "dt=0.01", time=30.0)),
                 [("energy_error", 1e-4)], cost_kinds=["wall"])
    m = t[t["integrator"] == "m"].set_index("entry")
    assert m.loc["m (adaptive)", "sweep"] == "rtol" and m.loc["m (adaptive)", "cost"] == 2.0
    assert m.loc["m (fixed dt)", "sweep"] == "dt" and m.loc["m (fixed dt)", "cost"] == 3.0
    # the fixed-step entry is ranked against the others, not hidden behind its adaptive twin
    assert m.loc["m (adaptive)", "verdict"] == "tie" and m.loc["m (fixed dt)", "verdict"] == "tie"
    assert one(t, "o")["entry"] == "o" and one(t, "o")["verdict"] == "slower"
    assert "`m (adaptive)`" in summary_lines(t)[0] and "`m (fixed dt)`" in summary_lines(t)[0]


def twins(**b_changes):
    """a and b at three settings; b's rows equal a's (one trajectory) unless changed."""
    rows = []
    for k, (dt, err) in enumerate([("0.02", 1e-3), ("0.01", 2.5e-4), ("0.005", 6.2e-5)]):
        errors = {m: err / (i + 2) for i, m in enumerate(ACCURACY) if m != "energy_error"}
        a = row("a", f"dt={dt}", error=err, time=1.0 + k, steps=50 * 2 ** k, **errors)
        fast = {c: 0.9 * a[c] for c in ("run_time", "run_time_low", "run_time_high")}  # b's times differ
        rows += [a, dict(a, integrator="b", **fast, **b_changes.get(dt, {}))]
    return table(*rows)


def test_two_methods_with_one_trajectory_are_ranked_once_and_the_other_says_why():
    t = cheapest(twins(), [("energy_error", 1e-4)], cost_kinds=["wall"])
    a, b = one(t, "a"), one(t, "b")
    assert a["entry"] == "a = b" and a["verdict"] == "winner"  # alone: b is not its tie
    assert b["verdict"] == "identical" and np.isnan(b["cost"]) and "the same trajectory as `a`" in b["note"]
    assert "tie" not in summary_lines(t)[0] and "`a = b`" in summary_lines(t)[0]


@pytest.mark.parametrize("change", [
    {"0.005": {"energy_error": 6.2e-5 * (1 + 1e-15)}},  # one error one ulp off at one setting
    {"0.01": {"steps": 101}},
    {"0.02": {"status": "diverged", "energy_error": np.nan}},
])
def test_methods_that_differ_anywhere_are_ranked_apart(change):
    from benchmark.cheapest import identical_methods

    runs = twins(**change)
    assert identical_methods(runs) == {}
    assert set(cheapest(runs, [("energy_error", 1e-4)])["verdict"]) <= {"winner", "tie", "slower"}


def test_one_shared_solution_is_not_evidence_of_one_trajectory():
    from benchmark.cheapest import identical_methods

    runs = twins()
    assert identical_methods(runs) == {("s", "b", "dt"): "a"}
    assert identical_methods(runs[runs["setting"] == "dt=0.01"]) == {}
    assert identical_methods(runs.drop(columns="attitude_error_max")) == {}  # not every error: no evidence


# ---- verdicts -----------------------------------------------------------------------------
def test_a_winner_only_when_its_interval_is_below_every_other():
    runs = table(row("a", "dt=0.01", time=1.0, low=0.9, high=1.4), row("b", "dt=0.01", time=3.0, low=2.5, high=4.0),
                 row("c", "dt=0.01", time=1.2, low=1.0, high=1.5))
    t = cheapest(runs, [("energy_error", 1e-4)], cost_kinds=["wall"], wall_resolution=0.0)
    assert [one(t, m)["verdict"] for m in "abc"] == ["tie", "slower", "tie"]
    t = cheapest(runs[runs["integrator"] != "c"], [("energy_error", 1e-4)], cost_kinds=["wall"], wall_resolution=0.0)
    assert [one(t, m)["verdict"] for m in "ab"] == ["winner", "slower"]
    b = one(t, "b")
    assert (b["ratio"], b["ratio_low"], b["ratio_high"]) == pytest.approx((3.0, 2.5 / 1.4, 4.0 / 0.9))


def test_the_wall_resolution_makes_close_times_a_tie_even_without_repeats():
    runs = table(row("a", "dt=0.01", time=1.0), row("b", "dt=0.01", time=1.9))
    t = cheapest(runs, [("energy_error", 1e-4)], cost_kinds=["wall"])
    assert WALL_RESOLUTION == 1.0 and set(t["verdict"]) == {"tie"}
    t = cheapest(runs.assign(run_time=[1.0, 2.1], run_time_high=[1.0, 2.1]), [("energy_error", 1e-4)],
                 cost_kinds=["wall"])
    assert list(t["verdict"]) == ["winner", "slower"]


def test_work_costs_within_the_work_resolution_are_a_tie():
    def verdicts(w):
        t = cheapest(table(row("a", "dt=0.01", work=1000.0), row("b", "dt=0.01", work=w)), [("energy_error", 1e-4)],
                     cost_kinds=["work"])
        return [one(t, m, "work")["verdict"] for m in "ab"]
    assert WORK_RESOLUTION == 0.10
    assert verdicts(1000.0) == verdicts(1099.0) == ["tie", "tie"]
    assert verdicts(1101.0) == ["winner", "slower"]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.01, 100.0), st.floats(1.0, 3.0), st.floats(1.0, 3.0)), min_size=1, max_size=6),
       st.floats(0.0, 1.0))
def test_no_winner_overlaps_another_interval_and_every_tie_overlaps_the_best(methods, resolution):
    runs = table(*(row(f"m{k}", "dt=0.01", time=c, low=c / lo, high=c * hi) for k, (c, lo, hi) in enumerate(methods)))
    t = cheapest(runs, [("energy_error", 1e-4)], cost_kinds=["wall"], wall_resolution=resolution)
    assert (t["cost_low"] <= t["cost"]).all() and (t["cost"] <= t["cost_high"]).all()
    assert (t["cost_high"] / t["cost_low"] >= math.sqrt(1 + resolution) ** 2 * (1 - 1e-12)).all()
    best = t.loc[t["cost"].idxmin()]
    assert (t["verdict"] == "winner").sum() <= 1
    for _, r in t.iterrows():
        others = t.drop(index=r.name)
        if r["verdict"] == "winner":
            assert (r["cost_high"] < others["cost_low"]).all()
        if r["verdict"] == "tie":
            assert r["cost_low"] <= best["cost_high"] and best["verdict"] == "tie"
        if r["verdict"] == "slower":
            assert r["cost_low"] > best["cost_high"]


# ---- two fresh runs: a winner stays a winner or joins the tie ------------------------------
def quick_sweep(rng, noise_factors, repeats=5, work_jitter=0.0):
    """A synthetic quick sweep (3 scenes, 7 methods, 3 settings each) with fixed true costs, some
    methods close together (1.3×, 1.7×, 2.2×); each row's timing repeats are the true cost times
    factors drawn from ``noise_factors`` (run_time their median, low the min, high the 90th
    percentile), and the adaptive methods' work counts move by up to ``work_jitter`` (their step
    sequences follow round-off)."""
    rows = []
    methods = {"lgvi": (1.0, 2, "dt"), "lgvi_sym": (1.3, 2, "dt"), "yoshida": (1.7, 4, "dt"), "suzuki": (2.2, 4, "dt"),
               "tsit5": (3.0, 5, "rtol"), "dop853": (30.0, 8, "rtol"), "radau": (60.0, 5, "rtol")}
    for scene, scale in (("fixed_length", 1.0), ("deployment", 1.7), ("retrieval", 2.9)):
        for name, (factor, order, axis) in methods.items():
            for k in range(3):
                true = 0.004 * scale * factor * 2.0 ** k
                error = 1e-3 * 2.0 ** (-order * k) * (0.3 if axis == "rtol" else 1.0)
                samples = true * rng.choice(noise_factors, size=repeats)
                work = 6000 * factor * 2.0 ** k * (1 + work_jitter * rng.uniform(-1, 1) if axis == "rtol" else 1)
                rows.append(row(name, f"{axis}={0.01 * 2.0 ** -k if axis == 'dt' else 10.0 ** (-4 - 2 * k):g}",
                                scene=scene, error=error, work=round(work), time=float(np.median(samples)),
                                low=float(samples.min()), high=float(np.quantile(samples, 0.9))))
    return table(*rows)


TARGETS = [("energy_error", 1e-4), ("energy_error", 3e-4)]


def winners_survive(first, second, **options):
    """The winners of ``first`` and those of them that are neither winner nor tie in ``second``."""
    a, b = (cheapest(r, TARGETS, **options) for r in (first, second))
    key = ["scene", "metric", "target", "cost_kind", "integrator"]
    both = a.merge(b, on=key, suffixes=("_1", "_2"))
    won = both[both["verdict_1"] == "winner"]
    return won, won[~won["verdict_2"].isin(["winner", "tie"])]


@pytest.mark.parametrize("repeats", [1, 5])
def test_two_fresh_runs_with_the_measured_noise_keep_every_winner_a_winner_or_in_the_tie(repeats):
    rng = np.random.default_rng(7)
    n_winners, lost_without_resolution = 0, 0
    for _ in range(10):
        first, second = (quick_sweep(rng, MEASURED_NOISE, repeats, work_jitter=0.05) for _ in range(2))
        won, lost = winners_survive(first, second)
        assert lost.empty, lost
        n_winners += len(won)
        lost_without_resolution += len(winners_survive(first, second, wall_resolution=0.0)[1])
    assert n_winners >= 30  # clear winners exist (by work, and by wall time for the far-apart methods)
    if repeats == 1:  # one timing sample has no spread: the wall resolution is what keeps the winners
        assert lost_without_resolution > 0


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(1.0, 1.0 + WALL_RESOLUTION), st.integers(1, 5))
def test_winners_survive_any_noise_within_the_resolution(seed, spread, repeats):
    # every timing statistic within a factor 1 + WALL_RESOLUTION of the true cost, every work
    # count within 1 + WORK_RESOLUTION: a winner provably stays a winner or joins the tie
    rng = np.random.default_rng(seed)
    noise = np.linspace(1.0, spread, 9)
    first, second = (quick_sweep(rng, noise, repeats, work_jitter=WORK_RESOLUTION / 2.1) for _ in range(2))
    assert winners_survive(first, second)[1].empty


# ---- summary lines ------------------------------------------------------------------------
def test_summary_lines_say_tie_and_give_ratios_with_their_range_never_1x_cheaper():
    runs = table(row("a", "dt=0.01", time=1.0, work=1000), row("b", "dt=0.01", time=1.3, work=1000),
                 row("c", "dt=0.01", time=5.0, work=1040), row("d", "dt=0.01", status="diverged"),
                 row("e", "dt=0.01", time=2.0, work=np.nan))
    lines = summary_lines(cheapest(runs, [("energy_error", 1e-4)]), {"energy_error": "energy error"})
    assert len(lines) == 1
    line = lines[0]
    assert line.startswith("- **s**, energy error ≤ 0.0001: By wall time, a tie of 3: `a` 1 s")
    assert "`b` 1.30× (" in line and "the next outside the tie, `c`, costs 5.00× (2.50×–10×) as much" in line
    assert "By work (work_evals), a tie of 3" in line and "`b` 1.00× (" in line and "`c` 1.04× (" in line
    assert "no cost for `e`" in line and "Not reached by `d`." in line
    assert "cheaper than" not in line and not re.search(r"(?<![\d.])1×", line)


def test_summary_line_of_a_winner_names_the_next_method_and_of_no_method():
    runs = table(row("a", "dt=0.01", time=1.0, work=1000), row("b", "dt=0.01", time=4.0, work=3000),
                 row("a", "dt=0.01", scene="hard", error=1.0))
    lines = summary_lines(cheapest(runs, [("energy_error", 1e-4)], cost_kinds=["work"]))
    assert lines[0] == "- **hard**, energy_error ≤ 0.0001: By work (work_evals), no method reached it. Not reached by `a`."
    assert lines[1] == ("- **s**, energy_error ≤ 0.0001: By work (work_evals), `a` is cheapest, 1e+03 evaluations "
                        "(953–1.05e+03); the next, `b`, costs 3.00× (2.73×–3.30×) as much; cost of `a` bounded by "
                        "the sweep's range (its coarsest setting already meets the target), not by the target.")


def test_a_cost_fixed_by_failed_coarser_steps_or_the_sweeps_range_says_so():
    runs = table(row("a", "dt=0.02", status="diverged"), row("a", "dt=0.01", error=1e-6, time=1.0),
                 row("b", "dt=0.02", error=1e-3, time=2.0), row("b", "dt=0.01", error=1e-5, time=4.0),
                 row("c", "rtol=1e-3", status="max_steps"), row("c", "rtol=1e-4", error=1e-6, time=9.0),
                 row("d", "dt=0.01", error=1e-6, time=30.0))
    t = cheapest(runs, [("energy_error", 1e-4)], cost_kinds=["wall"])
    assert {i: one(t, i)["bound"] for i in "abcd"} == {"a": "stability", "b": "accuracy", "c": "failures",
                                                       "d": "sweep range"}
    line = summary_lines(t)[0]
    assert "cost of `a` bounded by the stability limit (coarser steps did not finish), not by the target" in line
    assert "`b`" in line and "cost of `b`" not in line  # interpolated: fixed by the target


# ---- bad input ----------------------------------------------------------------------------
@pytest.mark.parametrize("change, message", [
    (lambda r: r.drop(columns="run_time_high"), "no column(s) run_time_high"),
    (lambda r: pd.concat([r, r]), "two rows for scene 's', integrator 'a', setting 'dt=0.01'"),
    (lambda r: r.assign(run_time_low=2.0), "run_time_low <= run_time <= run_time_high"),
    (lambda r: pd.concat([r, r.assign(setting="dt=0.005", dt=0.005, t_end=2.0)]), "several horizons"),
])
def test_a_bad_table_is_refused_naming_the_column(change, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        cheapest(change(table(row("a", "dt=0.01"))), [("energy_error", 1e-4)])


@pytest.mark.parametrize("kwargs, message", [
    ({"targets": [("energy_error", 0.0)]}, "target of 'energy_error' must be a positive number"),
    ({"targets": [("energy_error", 1e-4)], "cost_kinds": ["cpu"]}, "cost_kinds must be among"),
    ({"targets": [("energy_error", 1e-4)], "work_resolution": -0.1}, "work resolution must be a finite number >= 0"),
    ({"targets": [("no_such_error", 1e-4)]}, "no column(s) no_such_error"),
])
def test_bad_arguments_are_refused_before_any_work(kwargs, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        cheapest(table(row("a", "dt=0.01")), **kwargs)


# ---- runs that did not finish -------------------------------------------------------------
def test_failures_beyond_the_largest_finishing_step_are_expected_and_say_so():
    runs = table(row("a", "dt=0.02", status="diverged"), row("a", "dt=0.01", status="newton_failed"),
                 row("a", "dt=0.005"), row("b", "rtol=1e-4", status="max_steps"), row("b", "rtol=1e-6"))
    assert failure_summary(runs) == (
        "3 of 5 runs not ok, all expected: 2 at a step larger than every step at which the same method finished the "
        "scene (diverged 1, newton_failed 1); 1 stopped by their step or time budget (max_steps 1).")


def test_unexpected_failures_are_named():
    runs = table(row("a", "dt=0.02"), row("a", "dt=0.01", status="diverged"), row("b", "rtol=1e-4", status="diverged"),
                 row("c", "dt=0.01", status="error"), row("d", "dt=0.01", status="diverged"))
    causes = failure_causes(runs).set_index("integrator")["cause"]
    assert causes.to_dict() == {"a": "within its finishing range", "b": "adaptive", "c": "error",
                                "d": "no finished run"}
    text = failure_summary(runs)
    assert text.startswith("4 of 5 runs not ok, 4 not explained by a stability limit or a budget: `a` dt=0.01 on s "
                           "(diverged, within its finishing range)")


def test_the_stability_map_explains_a_failure_beyond_its_largest_stable_step():
    runs = table(row("a", "dt=0.01", status="diverged"), row("a", "dt=0.005", status="diverged"))
    stability = pd.DataFrame({"scene": ["s"], "integrator": ["a"], "largest_stable_dt": [0.0025]})
    assert set(failure_causes(runs, stability)["cause"]) == {"beyond the stability map's limit"}
    assert "2 at a step larger than the method's largest stable step in the stability map" in failure_summary(
        runs, stability)
    assert failure_summary(runs[runs["status"] == "x"]) == "All 0 runs ok."
