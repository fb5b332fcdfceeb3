"""reelbench.benchmark.runs.ranking: what a verdict ranks (entries), the work verdicts that say "tie" where the
intervals overlap, and why runs failed."""

import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reelbench.benchmark.runs.ranking import entry_name, failure_causes, failure_summary, presentation_rank, work_verdicts
from reelbench.benchmark.runs.sweep import PRESENTATION_ORDER


def row(integrator, setting, *, status="ok", error=1e-6, scene="s", **extra):
    axis, value = setting.split("=")
    return {"scene": scene, "integrator": integrator, "setting": setting,
            "dt": float(value) if axis == "dt" else float("nan"),
            "rtol": float(value) if axis == "rtol" else float("nan"),
            "t_end": 1.0, "status": status, "energy_error": error if status == "ok" else float("nan"), **extra}


def table(*rows):
    return pd.DataFrame(list(rows))


# ---- entries ------------------------------------------------------------------------------
def test_an_entry_names_its_axis_only_when_the_method_has_both_and_its_twins_after_equals():
    assert entry_name("lgvi", "dt", False) == "lgvi"
    assert entry_name("tsit5", "dt", True) == "tsit5 (fixed dt)"
    assert entry_name("tsit5", "rtol", True) == "tsit5 (adaptive)"
    assert entry_name("lgvi", "dt", False, ["lgvi_sym", "x"]) == "lgvi = lgvi_sym = x"


def test_methods_are_presented_in_the_projects_order_then_by_name():
    first, second = PRESENTATION_ORDER[:2]
    assert sorted(["zz_guest", "aa_guest", second, first], key=presentation_rank) == [first, second, "aa_guest",
                                                                                       "zz_guest"]


# ---- work verdicts ------------------------------------------------------------------------
def entry(name, cost, low=None, high=None):
    return {"entry": name, "cost": cost, "cost_low": cost if low is None else low,
            "cost_high": cost if high is None else high}


def test_a_winner_only_when_its_interval_is_below_every_other():
    rows = [entry("a", 1.0, 0.9, 1.4), entry("b", 3.0, 2.5, 4.0), entry("c", 1.2, 1.0, 1.5)]
    work_verdicts(rows)
    assert [r["verdict"] for r in rows] == ["tie", "slower", "tie"]
    rows = [entry("a", 1.0, 0.9, 1.4), entry("b", 3.0, 2.5, 4.0)]
    work_verdicts(rows)
    assert [r["verdict"] for r in rows] == ["winner", "slower"]
    b = rows[1]
    assert (b["ratio"], b["ratio_low"], b["ratio_high"]) == pytest.approx((3.0, 2.5 / 1.4, 4.0 / 0.9))


def test_rows_without_a_cost_are_left_as_they_are():
    rows = [entry("a", 2.0), {"entry": "b", "cost": float("nan"), "verdict": "not reached"}, {"entry": "c"}]
    work_verdicts(rows)
    assert [r.get("verdict") for r in rows] == ["winner", "not reached", None]
    nothing = [{"entry": "a", "cost": float("nan")}]
    work_verdicts(nothing)
    assert "verdict" not in nothing[0]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.01, 100.0), st.floats(1.0, 3.0), st.floats(1.0, 3.0)), min_size=1, max_size=6))
def test_no_winner_overlaps_another_interval_and_every_tie_overlaps_the_best(methods):
    rows = [entry(f"m{k}", c, c / lo, c * hi) for k, (c, lo, hi) in enumerate(methods)]
    work_verdicts(rows)
    t = pd.DataFrame(rows)
    best = t.loc[t["cost"].idxmin()]
    assert (t["verdict"] == "winner").sum() <= 1 and best["ratio"] == 1.0
    for _, r in t.iterrows():
        others = t.drop(index=r.name)
        if r["verdict"] == "winner":
            assert (r["cost_high"] < others["cost_low"]).all()
        if r["verdict"] == "tie":
            assert r["cost_low"] <= best["cost_high"] and best["verdict"] == "tie"
        if r["verdict"] == "slower":
            assert r["cost_low"] > best["cost_high"]
        assert r["ratio_low"] <= r["ratio"] <= r["ratio_high"]


# ---- runs that did not finish -------------------------------------------------------------
def test_inaccurate_runs_are_an_expected_cause_of_their_own():
    runs = table(row("a", "dt=0.02", status="inaccurate"), row("a", "dt=0.01"))
    assert failure_causes(runs)["cause"].tolist() == ["inaccurate"]
    assert failure_summary(runs) == ("1 of 2 runs not ok, all expected: 1 finished with an error beyond a sanity "
                                     "bound (no longer a solution) (inaccurate 1).")


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
