"""Results that can be trusted: the timing spread of a row, rows checked before they are kept,
a restricted run that merges into the table it writes to, words shortened at clause
boundaries, and an ETA from measured costs. Pure functions here; the sweeps that exercise them
end to end are in tests/test_resume_merge.py."""

import math

import numpy as np
import pytest

from reelbench.benchmark.core import engine
from reelbench.benchmark.runs import runner
from reelbench.benchmark.core import store
from reelbench.benchmark.runs import table
from reelbench.benchmark.core.report import shorten
from reelbench.benchmark.runs.sweep import MAX_REPEATS, TIMING_BUDGET


# ---- timing -------------------------------------------------------------------------------
@pytest.mark.parametrize("first, least, expected", [
    (0.001, 3, MAX_REPEATS),  # 2000 would fit: at most 30
    (0.1, 3, 20),  # floor(2 / 0.1)
    (0.9, 3, 3),  # floor(2 / 0.9) = 2: at least 3
    (0.9, 1, 2),  # --repeats 1 lowers the least
    (2.0, 3, 1),  # a single solve takes the budget: one sample
    (5.0, 3, 1),
    (float("nan"), 3, 1),
])
def test_timing_repeats_fill_the_budget_between_the_least_and_the_most(first, least, expected):
    assert runner.timing_repeats(first, least, budget=2.0) == expected


def test_the_timing_summary_is_the_median_with_min_and_p90_or_max():
    few = runner.timing_summary([3.0, 1.0, 2.0, 10.0])
    assert few == {"run_time": 2.5, "run_time_low": 1.0, "run_time_high": 10.0, "timing_repeats": 4}
    many = runner.timing_summary(list(range(1, 11)) + [float("nan")])  # 1..10: p90 = 9.1 (linear)
    assert many["timing_repeats"] == 10 and many["run_time"] == 5.5 and many["run_time_low"] == 1.0
    assert many["run_time_high"] == pytest.approx(9.1)
    assert math.isnan(runner.timing_summary([float("nan")])["run_time"])


def test_a_run_is_timed_as_often_as_its_first_solve_allows():
    calls = []
    first = TIMING_BUDGET / 4
    cols = runner._timing(first, lambda: calls.append(1) or first * (0.8 + 0.01 * len(calls)), least=3)
    # budget / first = 4 solves, each a repeat of the same unbudgeted work (the first, run within
    # its budget, only sets the count: it is not a sample)
    assert len(calls) == 4 and cols["timing_repeats"] == 4
    assert cols["run_time"] == pytest.approx(first * 0.825) and cols["run_time_high"] == pytest.approx(first * 0.84)


def test_us_per_eval_is_empty_without_an_evaluation_count():
    assert runner.us_per_eval(0.002, 1000.0) == pytest.approx(2.0)
    assert math.isnan(runner.us_per_eval(0.002, float("nan"))) and math.isnan(runner.us_per_eval(0.002, 0.0))


# ---- rows checked before they are trusted -------------------------------------------------
def _row(**values) -> dict:
    """A row as the runner writes it (its digest over ``values``)."""
    row = {"scene": "fixed_length", "scene_key": "abc", "integrator": "lgvi", "setting": "dt=0.01", "dt": 0.01,
           "rtol": np.nan, "atol": np.nan, "t_end": 1.0, "status": "ok", "reason": "", "rhs": "closed_form",
           "steps": 100, "rhs_evals": np.nan, "jac_evals": np.nan, "lu_decompositions": np.nan,
           "newton_iterations": 300.0, "work_evals": 300.0, "run_time": 0.002, "run_time_low": 0.0015,
           "run_time_high": 0.004, "timing_repeats": 30, "compile_time": 2.0, "energy_error": 3e-5,
           "pi3_error": 1e-13, "orthogonality_error": 1e-14, "position_error_final": 9e-3,
           "position_error_max": 1e-2, "attitude_error_final": 0.2, "attitude_error_max": 0.2, "t_reached": 1.0,
           "implementation": "jax-compiled", "load_avg": 2.5, "us_per_eval": 6.7, **values}
    return runner.finish_row(row, "k1")


def _round_trip(tmp_path, rows) -> table.StoredRuns:
    path = tmp_path / "runs.csv"
    store.write_table(path, runner.runs_frame(rows))
    said = []
    got = table.read_runs(path, log=said.append)
    got.said = said
    return got


def test_rows_written_by_the_runner_are_trusted_after_a_round_trip_through_csv(tmp_path):
    failed = runner.finish_row({**_row(), "setting": "dt=0.02", "dt": 0.02, "status": "diverged",
                                "reason": "energy balance error 1e5 J; kept up to t = 0.08 s"}, "k2")
    got = _round_trip(tmp_path, [_row(), failed])
    assert not got.rejected and len(got.rows) == 2 and got.unverified == 0, got.rejected
    assert [r["run_key"] for r in got.rows if got.reusable(r)] == ["k1", "k2"]


@pytest.mark.parametrize("edit, why", [
    ({"energy_error": 1e-20}, "do not match the digest"),  # plausible, but not what was computed
    ({"status": "diverged"}, "do not match the digest"),  # the writer drops its errors: the digest sees it
    ({"position_error_final": -5.0}, "position_error_final = -5.0 is outside its range"),
    ({"run_time": "fast"}, "run_time = 'fast' is not a number"),
    ({"status": "great"}, "status 'great' is not a status of the runs table"),
    ({"run_time_low": 0.01}, "run_time_low <= run_time <= run_time_high"),
    ({"steps": float("inf")}, "steps = inf is outside its range"),
])
def test_a_row_edited_by_hand_is_not_trusted_and_named(tmp_path, edit, why):
    got = _round_trip(tmp_path, [{**_row(), **edit}, _row(setting="dt=0.005", dt=0.005)])
    assert len(got.rejected) == 1 and why in got.rejected[0][1], got.rejected
    assert len(got.rows) == 1
    assert any("fixed_length/lgvi/dt=0.01" in line and why in line for line in got.said), got.said


def test_a_diverged_run_edited_to_ok_is_caught_by_its_digest_and_its_missing_errors(tmp_path):
    diverged = runner.finish_row({**_row(), "status": "diverged", "reason": "energy grew"}, "k1")
    edited = {**diverged, "status": "ok"}
    assert "without any accuracy value" in table.check_row(edited)  # also without its digest
    faked = {**edited, "energy_error": 1e-9, "position_error_final": 1e-9}  # errors made up too
    assert "digest" in table.check_row(faked)


def test_a_row_without_a_digest_is_checked_by_its_ranges_alone():
    old = {k: v for k, v in _row().items() if k != "row_digest"}
    assert table.check_row(old) is None
    assert "outside its range" in table.check_row({**old, "energy_error": -1.0})


def test_an_unreadable_table_is_recomputed_not_a_crash(tmp_path):
    path = tmp_path / "runs.csv"
    path.write_bytes(b"\x00\xff garbage \n\x01")
    said = []
    got = table.read_runs(path, log=said.append)
    assert got.rows == [] and got.rejected == []
    assert got.aside is not None and got.aside.read_bytes() == path.read_bytes()  # kept intact beside it


# ---- merging a run into the table of its --out --------------------------------------------
def _r(scene, integ, setting, **kw):
    return {"scene": scene, "integrator": integ, "setting": setting, **kw}


def test_a_run_replaces_its_own_rows_in_place_and_adds_the_others_beside_their_method():
    base = [_r("a", "lgvi", "dt=0.01", v=1), _r("a", "lgvi", "dt=0.005", v=1), _r("a", "rk45", "rtol=1e-4", v=1),
            _r("b", "lgvi", "dt=0.01", v=1)]
    new = [_r("a", "lgvi", "dt=0.005", v=2), _r("a", "lgvi", "dt=0.0025", v=2), _r("c", "tsit5", "dt=0.01", v=2)]
    merged = store.merge_rows(base, new)
    assert [(r["scene"], r["integrator"], r["setting"], r["v"]) for r in merged] == [
        ("a", "lgvi", "dt=0.01", 1), ("a", "lgvi", "dt=0.005", 2), ("a", "lgvi", "dt=0.0025", 2),
        ("a", "rk45", "rtol=1e-4", 1), ("b", "lgvi", "dt=0.01", 1), ("c", "tsit5", "dt=0.01", 2)]
    assert store.merge_rows([], new) == new and store.merge_rows(base, []) == base


def test_a_run_over_another_horizon_or_other_scene_values_cannot_join():
    base = [_r("fixed_length", "lgvi", "dt=0.01", t_end=10.0, scene_key="k10"),
            _r("deployment", "lgvi", "dt=0.01", t_end=2.0)]  # an older row: no physics hash
    assert table.merge_conflicts(base, {"fixed_length": (10.0, "k10"), "deployment": (2.0, "any")}) == []
    assert table.merge_conflicts(base, {"retrieval": (1.0, "x")}) == []
    (quick,) = table.merge_conflicts(base, {"fixed_length": (1.0, "k10")})
    assert "scene 'fixed_length'" in quick and "t_end = 10 s, this run's over 1 s" in quick
    (other,) = table.merge_conflicts(base, {"fixed_length": (10.0, "k20")})
    assert "other scene values" in other and "k10" in other


def test_output_keys_keep_a_file_only_while_its_inputs_are_the_same(tmp_path):
    keys = store.OutputKeys(tmp_path / "figures.json")
    assert not keys.fresh("a.png", "k1")
    (tmp_path / "a.png").write_bytes(b"png")
    keys.record("a.png", "k1")
    again = store.OutputKeys(tmp_path / "figures.json")
    assert again.fresh("a.png", "k1") and not again.fresh("a.png", "k2")
    (tmp_path / "a.png").unlink()
    assert not again.fresh("a.png", "k1")  # a deleted file is made again
    rows = [{"x": 1, "y": float("nan"), "z": "t"}]
    assert store.rows_key(rows) == store.rows_key([{"z": "t", "y": "", "x": 1.0}])


# ---- words --------------------------------------------------------------------------------
def test_a_reason_is_shortened_at_a_clause_boundary_or_printed_in_full():
    reason = ("energy balance error |E - W - E0| = 1.036e+05 J at t = 0.1 s exceeds the bound 1337 J "
              "(ENERGY_GROWTH_FACTOR x the scene's energy scale); trajectory kept up to the previous save point")
    short = shorten(reason, 120)
    assert len(short) <= 120 and short.endswith(" …") and reason.startswith(short[:-2])
    assert short[:-2].endswith("1337 J")  # cut before the parenthesis, not inside a word or a number
    assert shorten("Newton failed. The step was 0.01 s and the residual 3e2 after 20 iterations", 40) == \
        "Newton failed. …"
    unbroken = "x" * 200
    assert shorten(unbroken, 50) == unbroken
    assert shorten("short", 50) == "short"


def test_describe_run_never_cuts_a_reason_mid_word():
    row = {"scene": "s", "integrator": "m", "setting": "dt=0.01", "status": "diverged",
           "reason": "energy balance error 1.6e3 J at t = 0.22 s exceeds the bound 1337 J (a factor of the scene's "
                     "energy scale); trajectory kept up to t = 0.2 s, the previous save point of the run"}
    text = runner.describe_run(row)
    assert text.endswith("(a factor of the scene's energy scale) …"), text  # cut at the "; ", a clause boundary


# ---- the ETA ------------------------------------------------------------------------------
def test_the_eta_weighs_the_jobs_left_by_their_predicted_cost(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(engine.time, "perf_counter", lambda: clock[0])
    said = []
    cost = [10.0, 1.0, 1.0, 10.0, 1.0, 1.0]  # per job: compile on the first of each method
    p = engine.Progress(6, cost=lambda i: cost[i], log=said.append)
    clock[0] += 5.0
    p.done(0, {})  # 10 s of predicted cost done in 5 s: the 14 left take 7
    assert p.seconds_left() == pytest.approx(7.0)
    clock[0] += 15.0
    p.done(3, {})  # 20 in 20 s: the 4 left take 4
    assert p.seconds_left() == pytest.approx(4.0)
    assert "about 7 s left" in said[0] and said[0].startswith("[1/6]")


def test_without_costs_every_job_counts_the_same(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(engine.time, "perf_counter", lambda: clock[0])
    p = engine.Progress(4, log=lambda s: None)
    clock[0] = 3.0
    p.done(0, {})
    assert p.seconds_left() == pytest.approx(9.0)


def test_resumed_jobs_count_in_the_total_not_in_the_rate(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(engine.time, "perf_counter", lambda: clock[0])
    said = []
    p = engine.Progress(4, rows={0: {}, 1: {}}, cost=lambda i: [1.0, 1.0, 2.0, 4.0][i], log=said.append)
    clock[0] = 4.0
    p.done(2, {})  # 2 of predicted cost in 4 s (the kept jobs took none of them): the 4 left take 8
    assert said == ["[3/4] {}  (4 s elapsed, about 8 s left)"]


def test_setup_calls_each_say_when_they_are_done():
    said = []
    rows = engine.run_jobs(lambda x: {"x": x}, [1, 2], workers=0, setup=[lambda: None, lambda: None],
                           setup_labels=["reference a", "reference b"], log=said.append)
    assert [r["x"] for r in rows] == [1, 2]
    assert said[0].startswith("[1/2] reference a ready") and said[1].startswith("[2/2] reference b ready")


# ---- the plugin workflow ------------------------------------------------------------------
def test_the_stability_map_runs_a_registered_plugin_when_named_not_by_default():
    """A plugin is a guest: the committed map holds the project's methods unless one is named."""
    from reelbench.benchmark.studies import stability
    from reelbench.integrators import FixedStepMethod, register, registry

    @register
    class Plugin(FixedStepMethod):
        name = "trust_plugin_euler"
        order = 1
        description = "test only"

        def step(self, ode, y, t, h):
            return y + h * ode.f(t, y)

    try:
        assert "trust_plugin_euler" not in stability.default_integrators()
        assert not any(j.integrator == "trust_plugin_euler" for j in stability.jobs_for())
        assert "lgvi" in stability.default_integrators()
        assert any(j.integrator == "trust_plugin_euler" for j in stability.jobs_for(integrators=["trust_plugin_euler"]))
    finally:
        registry.unregister("trust_plugin_euler")


def test_a_first_solve_as_long_as_the_budget_is_its_own_timing_and_nothing_is_solved_again():
    calls = []
    row = runner._timing(0.8, lambda: calls.append(1) or 0.7, 3)  # budget 0.5 s: one solve fills it
    assert calls == [] and row["run_time"] == 0.8 and row["timing_repeats"] == 1
    row = runner._timing(0.1, lambda: calls.append(1) or 0.1, 3)  # a short run is timed again, 5 times
    assert len(calls) == 5 and row["timing_repeats"] == 5
