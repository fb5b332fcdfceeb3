"""Each rule of the benchmark stated once: the places that used to restate one now read it, or
(where they cannot import it) are pinned to it here."""

import math

import pytest

from benchmark.core import policy
from benchmark.core.policy import Setting


def test_a_setting_carries_its_label_its_solve_arguments_and_parses_back():
    fixed, adaptive = Setting.fixed(0.0025), Setting.adaptive(1e-6)
    assert fixed.label() == "dt=0.0025" and adaptive.label() == "rtol=1e-06"
    assert adaptive.atol == 1e-6 * policy.ATOL_FACTOR == policy.atol_for(1e-6)
    assert fixed.solve_kwargs() == {"dt": 0.0025} and adaptive.solve_kwargs() == {"rtol": 1e-6, "atol": 1e-8}
    for s in (fixed, adaptive, Setting.on_axis("dt", 0.02 / 2 ** 7), Setting.adaptive(1e-4, 3e-7)):
        back = Setting.parse(s.label() + (f", atol={s.atol!r}" if s.atol is not None else ""))
        assert back == s and back.label() == s.label()
    assert Setting.on_axis("rtol", 1.2345678e-5).label(digits=4) == "rtol=1.235e-05"  # the answer's labels
    assert policy.axis_of("order(dt)") is None and math.isnan(policy.setting_value("nan"))
    with pytest.raises(ValueError):
        Setting(dt=0.01, rtol=1e-6)
    with pytest.raises(ValueError):
        Setting.parse("kind=7")


def test_the_sweep_and_the_answer_solve_a_setting_alike():
    from benchmark.answer import answer
    from benchmark.runs.sweep import Task, build_tasks

    for axis, value in (("dt", 0.005), ("rtol", 1e-6)):
        task = Task("fixed_length", "tsit5", **vars(Setting.on_axis(axis, value)), t_end=1.0)
        assert task.solve_kwargs() == answer.solve_kwargs(axis, value, 1.0)
        assert task.setting == Setting.on_axis(axis, value).label()
    adaptive = [t for t in build_tasks(["fixed_length"], ["rk45"], quick=True)]
    assert adaptive and all(t.atol == policy.atol_for(t.rtol) and t.save_every == policy.SAVE_EVERY for t in adaptive)


def test_the_budgets_and_the_resolution_are_read_from_the_policy():
    from benchmark.answer import answer
    from benchmark.studies import horizon
    from benchmark.core import options
    from benchmark.answer import paired
    from benchmark.runs import runner
    from benchmark.answer import search

    assert runner.SolveBudget() == runner.SolveBudget(policy.SOLVE_MAX_STEPS, policy.SOLVE_TIME_LIMIT)
    assert (options.SOLVE_MAX_STEPS, options.SOLVE_TIME_LIMIT) == (policy.SOLVE_MAX_STEPS, policy.SOLVE_TIME_LIMIT)
    assert horizon.MAX_STEPS == policy.SOLVE_MAX_STEPS
    assert paired.BUDGET == answer.TimingJob("s", 1, "m", 1.0, ()).budget == policy.PAIRED_BUDGET
    assert search.RESOLUTION == paired.PRECISION == policy.RESOLUTION
    assert paired.EQUIVALENCE == policy.TIE_MARGIN and paired.RACE_MARGIN == 2 * policy.TIE_MARGIN


def test_every_reference_setup_is_the_policy_s():
    from benchmark.studies import orders
    from benchmark.core import reference

    assert reference.REFERENCE_METHOD is policy.REFERENCE_METHOD
    assert (orders.REFERENCE_METHOD, orders.REFERENCE_DT) == (policy.ORDERS_REFERENCE_METHOD,
                                                              policy.ORDERS_REFERENCE_DT)
    assert orders.CHECK_METHOD is policy.ORDERS_CHECK_METHOD


def test_the_status_sets_are_named_once_beside_the_statuses():
    from benchmark.runs import metrics
    from benchmark.runs import ranking
    from benchmark.answer import search
    from benchmark.runs import table
    from integrators.base import (BUDGET_STATUSES, FINISHED_STATUSES, RETRY_STATUSES, TABLE_ONLY_STATUSES, Status,
                                  is_finished)

    assert FINISHED_STATUSES == (Status.OK.value,) and is_finished("ok") and not is_finished(float("nan"))
    assert set(BUDGET_STATUSES) | set(RETRY_STATUSES) <= set(table.statuses())
    assert len(table.statuses()) == len(set(table.statuses())) == len(Status) + len(TABLE_ONLY_STATUSES)
    assert metrics.INACCURATE in TABLE_ONLY_STATUSES
    assert search._stopped_by_budget(BUDGET_STATUSES[0]) and not search._stopped_by_budget("ok")
    assert ranking.BUDGET_STATUSES is BUDGET_STATUSES


@pytest.mark.parametrize("t_end, dt", [(1.0, 0.3), (1.0, 0.25), (2.56, 0.16), (0.5, 0.0025 * 3), (10.0, 0.02 / 2 ** 8),
                                       (1.0, 1.0), (0.07, 0.02)])
def test_the_command_line_counts_the_steps_and_the_memory_the_integrators_do(t_end, dt):
    """options.run_size restates two integrator rules (it must not import the integrators package):
    its step count is the loop's, also where dt does not divide t_end, and its saved size is the one
    the integrators refuse beyond, with the same limits."""
    from benchmark.core import options
    from integrators import lifecycle
    from integrators.base import fixed_step_count, fixed_step_grid
    from models import load_scene

    scene = load_scene("deployment", elements=3)
    size = options.run_size(scene, t_end, 0.02, dt)
    assert size["steps"] == fixed_step_count(t_end, dt) == fixed_step_grid(t_end, dt, 0.02)[0]
    _, n_run, _ = lifecycle.step_indices(t_end, dt, 0.02, None)
    assert size["steps"] == n_run
    assert (size["points"], size["bytes"]) == lifecycle.saved_size(scene, t_end, 0.02, dt)
    assert options.run_size(scene, t_end, 0.02)["bytes"] == lifecycle.saved_size(scene, t_end, 0.02)[1]
    assert (options.STEPS_REFUSE, options.MEMORY_REFUSE) == (lifecycle.MAX_PLANNED_STEPS, lifecycle.MAX_SAVED_BYTES)


def test_the_longest_horizon_is_the_scene_files():
    from integrators import lifecycle
    from models.schema import PLAUSIBLE

    assert lifecycle.T_END_MAX == PLAUSIBLE["t_end"][1]


def test_a_row_s_identity_is_one_rule_and_a_new_metric_is_range_checked_on_read_back(monkeypatch):
    from benchmark.studies import check
    from benchmark.runs import metrics
    from benchmark.runs import reproducibility
    from benchmark.runs import table
    from benchmark.core import store
    from benchmark.runs.sweep import Task

    task = Task("fixed_length", "lgvi", dt=0.01)
    row = {"scene": "fixed_length", "integrator": "lgvi", "setting": task.setting, "status": "ok", "run_time": 0.1,
           "energy_error": 1e-5}
    assert task.identity == store.identity_of(row) and check.KEY == reproducibility.KEY == list(policy.ROW_IDENTITY)
    assert table.error_columns() == tuple(metrics.ACCURACY) and table.check_row(row) is None
    monkeypatch.setattr(metrics, "ACCURACY", [*metrics.ACCURACY, "new_error"])
    assert "new_error" in table.check_row({**row, "new_error": -1.0})


def test_the_output_places_are_the_policy_s():
    from benchmark.answer import answer
    from benchmark.studies import check
    from benchmark.cli import run as cli_run
    from benchmark.studies import grid
    from benchmark.core import store

    assert check.BASELINE == policy.BASELINE_FILE and answer.COMMITTED_ANSWER == policy.RESULTS
    assert cli_run.GRID_OUT == str(policy.GRID_DIR) and grid.COMMITTED_RESULTS == store.ROOT / policy.GRID_DIR


def test_the_defaults_of_a_request_are_the_command_line_s():
    from benchmark.studies import check
    from benchmark.studies import grid
    from benchmark.runs import sweep

    request = grid.SweepRequest(out=".", scenes=("fixed_length",), quick=True)
    assert (request.executor, request.repeats) == (sweep.DEFAULT_EXECUTOR, sweep.MIN_REPEATS)
    assert request.sweep_t_end == sweep.sweep_t_end(None, True) == sweep.QUICK_T_END
    assert sweep.sweep_dts(None, True) == sweep.QUICK_DTS and sweep.sweep_dts((0.3,), True) == (0.3,)
    assert check.RegressionTolerance() == check.RegressionTolerance(policy.CHECK_FACTOR, policy.CHECK_ORDER_MARGIN)


def test_the_reel_reversal_table_and_the_order_ladders_compute_an_order_alike():
    from types import SimpleNamespace

    from benchmark.studies import orders
    from benchmark.studies import reel_reversal

    errors = [reel_reversal.Errors(1e-3, 2e-3, 4e-3), reel_reversal.Errors(2.5e-4, 2.5e-4, 1e-3)]
    rows = [{"method": "lgvi", "h": h, "status": "ok", **{f"error_{k}": v for k, v in e._asdict().items()}}
            for h, e in zip((0.01, 0.005), errors)]
    text = reel_reversal.table(SimpleNamespace(name="s", string=SimpleNamespace(elements=2)), 1.0, [0.5], rows)
    assert text.splitlines()[-1].endswith("| 2.00 / 3.00 / 2.00 |")
    assert orders.slopes((0.01, 0.005), (1e-3, 2.5e-4))[0] == pytest.approx(2.0)
