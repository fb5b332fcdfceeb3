"""Each rule of the benchmark stated once: the places that used to restate one now read it, or
(where they cannot import it) are pinned to it here."""

import math

import pytest

from reelbench.benchmark.core import policy
from reelbench.benchmark.core.policy import Setting


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
    from reelbench.benchmark.answer import jobs
    from reelbench.benchmark.runs.sweep import Task, build_tasks

    for axis, value in (("dt", 0.005), ("rtol", 1e-6)):
        task = Task("fixed_length", "tsit5", **vars(Setting.on_axis(axis, value)), t_end=1.0)
        assert task.solve_kwargs() == jobs.solve_kwargs(axis, value, 1.0)
        assert task.setting == Setting.on_axis(axis, value).label()
    adaptive = [t for t in build_tasks(["fixed_length"], ["rk45"], quick=True)]
    assert adaptive and all(t.atol == policy.atol_for(t.rtol) and t.save_every == policy.SAVE_EVERY for t in adaptive)


def test_the_budgets_and_the_resolution_are_read_from_the_policy():
    from reelbench.benchmark.answer import jobs
    from reelbench.benchmark.studies import horizon
    from reelbench.benchmark.core import options
    from reelbench.benchmark.answer import paired
    from reelbench.benchmark.runs import runner
    from reelbench.benchmark.answer import search

    assert runner.SolveBudget() == runner.SolveBudget(policy.SOLVE_MAX_STEPS, policy.SOLVE_TIME_LIMIT)
    assert (options.SOLVE_MAX_STEPS, options.SOLVE_TIME_LIMIT) == (policy.SOLVE_MAX_STEPS, policy.SOLVE_TIME_LIMIT)
    assert horizon.MAX_STEPS == policy.SOLVE_MAX_STEPS
    assert paired.BUDGET == jobs.TimingJob("s", 1, "m", 1.0, ()).budget == policy.PAIRED_BUDGET
    assert search.RESOLUTION == paired.PRECISION == policy.RESOLUTION
    assert paired.EQUIVALENCE == policy.TIE_MARGIN and paired.RACE_MARGIN == 2 * policy.TIE_MARGIN


def test_every_reference_setup_is_the_policy_s():
    from reelbench.benchmark.studies import orders
    from reelbench.benchmark.core import reference

    assert reference.REFERENCE_METHOD is policy.REFERENCE_METHOD
    assert (orders.REFERENCE_METHOD, orders.REFERENCE_DT) == (policy.ORDERS_REFERENCE_METHOD,
                                                              policy.ORDERS_REFERENCE_DT)
    assert orders.CHECK_METHOD is policy.ORDERS_CHECK_METHOD


def test_the_status_sets_are_named_once_beside_the_statuses():
    from reelbench.benchmark.runs import metrics
    from reelbench.benchmark.runs import ranking
    from reelbench.benchmark.answer import search
    from reelbench.benchmark.runs import table
    from reelbench.integrators.base import (BUDGET_STATUSES, FINISHED_STATUSES, RETRY_STATUSES, TABLE_ONLY_STATUSES, Status,
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
    from reelbench.benchmark.core import options
    from reelbench.integrators import lifecycle
    from reelbench.integrators.base import fixed_step_count, fixed_step_grid
    from reelbench.models import load_scene

    scene = load_scene("deployment", elements=3)
    size = options.run_size(scene, t_end, 0.02, dt)
    assert size["steps"] == fixed_step_count(t_end, dt) == fixed_step_grid(t_end, dt, 0.02)[0]
    _, n_run, _ = lifecycle.step_indices(t_end, dt, 0.02, None)
    assert size["steps"] == n_run
    assert (size["points"], size["bytes"]) == lifecycle.saved_size(scene, t_end, 0.02, dt)
    assert options.run_size(scene, t_end, 0.02)["bytes"] == lifecycle.saved_size(scene, t_end, 0.02)[1]
    assert (options.STEPS_REFUSE, options.MEMORY_REFUSE) == (lifecycle.MAX_PLANNED_STEPS, lifecycle.MAX_SAVED_BYTES)


def test_the_longest_horizon_is_the_scene_files():
    from reelbench.integrators import lifecycle
    from reelbench.models.schema import PLAUSIBLE

    assert lifecycle.T_END_MAX == PLAUSIBLE["t_end"][1]


def test_a_row_s_identity_is_one_rule_and_a_new_metric_is_range_checked_on_read_back(monkeypatch):
    from reelbench.benchmark.studies import check
    from reelbench.benchmark.runs import metrics
    from reelbench.benchmark.runs import reproducibility
    from reelbench.benchmark.runs import table
    from reelbench.benchmark.core import store
    from reelbench.benchmark.runs.sweep import Task

    task = Task("fixed_length", "lgvi", dt=0.01)
    row = {"scene": "fixed_length", "integrator": "lgvi", "setting": task.setting, "status": "ok", "run_time": 0.1,
           "energy_error": 1e-5}
    assert task.identity == store.identity_of(row) and check.KEY == reproducibility.KEY == list(policy.ROW_IDENTITY)
    assert table.error_columns() == tuple(metrics.ACCURACY) and table.check_row(row) is None
    monkeypatch.setattr(metrics, "ACCURACY", [*metrics.ACCURACY, "new_error"])
    assert "new_error" in table.check_row({**row, "new_error": -1.0})


def test_the_output_places_are_the_policy_s():
    from reelbench.benchmark.answer import answer
    from reelbench.benchmark.studies import check
    from reelbench.benchmark.cli import run as cli_run
    from reelbench.benchmark.studies import grid
    from reelbench.benchmark.core import store

    assert check.BASELINE == policy.BASELINE_FILE and answer.COMMITTED_ANSWER == policy.RESULTS
    assert cli_run.GRID_OUT == str(policy.GRID_DIR) and grid.COMMITTED_RESULTS == store.ROOT / policy.GRID_DIR


def test_the_defaults_of_a_request_are_the_command_line_s():
    from reelbench.benchmark.studies import check
    from reelbench.benchmark.studies import grid
    from reelbench.benchmark.runs import sweep

    request = grid.SweepRequest(out=".", scenes=("fixed_length",), quick=True)
    assert (request.executor, request.repeats) == (sweep.DEFAULT_EXECUTOR, sweep.MIN_REPEATS)
    assert request.sweep_t_end == sweep.sweep_t_end(None, True) == sweep.QUICK_T_END
    assert sweep.sweep_dts(None, True) == sweep.QUICK_DTS and sweep.sweep_dts((0.3,), True) == (0.3,)
    assert check.RegressionTolerance() == check.RegressionTolerance(policy.CHECK_FACTOR, policy.CHECK_ORDER_MARGIN)


def test_the_reel_reversal_table_and_the_order_ladders_compute_an_order_alike():
    from types import SimpleNamespace

    from reelbench.benchmark.core.order import successive_orders
    from reelbench.benchmark.studies import reel_reversal

    errors = [reel_reversal.Errors(1e-3, 2e-3, 4e-3), reel_reversal.Errors(2.5e-4, 2.5e-4, 1e-3)]
    rows = [{"method": "lgvi", "h": h, "status": "ok", **{f"error_{k}": v for k, v in e._asdict().items()}}
            for h, e in zip((0.01, 0.005), errors)]
    text = reel_reversal.table(SimpleNamespace(name="s", string=SimpleNamespace(elements=2)), 1.0, [0.5], rows)
    assert text.splitlines()[-1].endswith("| 2.00 / 3.00 / 2.00 |")
    assert successive_orders((0.01, 0.005), (1e-3, 2.5e-4))[0] == pytest.approx(2.0)


# ---- the observed order (R29): one function, every study calls it --------------------------
def _ladder(order, sizes=(0.04, 0.02, 0.01, 0.005, 0.0025), c=3.0):
    import numpy as np

    h = np.asarray(sizes, float)
    return h, c * h ** order


@pytest.mark.parametrize("order", [1, 2, 4, 8])
def test_the_observed_order_of_a_ladder_of_known_order(order):
    import numpy as np

    from reelbench.benchmark.core.order import fitted_order, last_order, successive_orders

    h, e = _ladder(order)
    assert np.allclose(successive_orders(h, e), order) and len(successive_orders(h, e)) == len(h) - 1
    assert np.allclose(successive_orders(h[::-1], e[::-1]), order)  # either direction
    assert last_order(h, e) == pytest.approx(order) and fitted_order(h, e) == pytest.approx(order)
    assert math.isnan(last_order(h[:1], e[:1])) and math.isnan(fitted_order((0.01, 0.01), (1e-3, 2e-3)))
    # a ladder whose last halving leaves the asymptotic range (order 1 there): the last pair and the
    # fit tell it apart
    e2 = e.copy()
    e2[-1] = e2[-2] / 2
    assert order == 1 or last_order(h, e2) == pytest.approx(1.0) and order > fitted_order(h, e2) > 1.0


def test_every_study_takes_the_observed_order_from_one_place(monkeypatch):
    """The drift check, the order ladders, reel reversal, the slack orders and the contract each
    call `benchmark.core.order`: none restates the formula."""
    import re
    from pathlib import Path

    import numpy as np
    import pandas as pd

    from reelbench.benchmark.runs import metrics
    from reelbench.benchmark.studies import slack_orders

    h, e = _ladder(2.0)
    runs = pd.DataFrame({"scene": "s", "integrator": "m", "dt": h, "steps": np.round(1.0 / h), "status": "ok",
                         "position_error_final": e})
    got = metrics.observed_orders(runs).iloc[0]
    assert got.observed_order == pytest.approx(2.0) and got.finest_pair_order == pytest.approx(2.0)
    table = pd.DataFrame({"scene": "s", "integrator": "m", "dt": h, "position_error": e, "energy_error": e ** 2,
                          "reference_slack_share": 0.0})
    row = slack_orders.orders(table).iloc[0]
    assert np.allclose(row.position_orders, 2.0) and np.allclose(row.energy_orders, 4.0)
    # the formulas, by their shape: log2 of a ratio, a difference of logs, a fit of logs
    root = Path(__file__).resolve().parents[1] / "benchmark"
    shapes = re.compile(r"np\.log2\(|np\.diff\(np\.log\(|polyfit\(np\.log\(")
    found = [f"{p.relative_to(root)}:{k}" for p in sorted(root.rglob("*.py")) if p.name != "order.py"
             for k, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if shapes.search(line)]
    # lgvi_speed fits how the cost grows with N (an exponent, not an order of convergence)
    assert found == [f for f in found if f.startswith("studies/lgvi_speed.py")], found
    callers = {"runs/metrics.py", "studies/orders.py", "studies/reel_reversal.py", "studies/slack_orders.py",
               "contract/integrator.py"}
    for name in callers:
        assert "from reelbench.benchmark.core.order import" in (root / name).read_text(encoding="utf-8"), name


# ---- the verdicts' words (R23): each listed once, beside the code that decides them ---------
def _string_constants(words: set) -> list[str]:
    """file:line of every string literal in benchmark/ that is one of ``words``."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "benchmark"
    return [f"{p.relative_to(root)}:{n.lineno}" for p in sorted(root.rglob("*.py"))
            for n in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in words]


def test_each_verdict_word_is_written_once():
    from reelbench.benchmark.runs import reproducibility

    answer_words = {*policy.RANKED_VERDICTS, *policy.UNRANKED_VERDICTS}
    assert policy.BEST_VERDICTS == policy.RANKED_VERDICTS[:2] and len(answer_words) == 7
    assert _string_constants(answer_words) == ["core/policy.py:" + _line_of("WINNER, TIE, SLOWER")] * 3 + [
        "core/policy.py:" + _line_of("IDENTICAL, NO_FLOPS_COUNT")] * 4
    found = _string_constants(set(reproducibility.VERDICTS))
    assert len(found) == 6 and {f.split(":")[0] for f in found} == {"runs/reproducibility.py"}, found


def _line_of(text: str) -> str:
    lines = policy.__loader__.get_source(policy.__name__).splitlines()
    return str(next(k for k, line in enumerate(lines, 1) if line.startswith(text)))


def test_the_rankings_and_the_answer_give_the_verdicts_of_policy():
    from reelbench.benchmark.answer import paired
    from reelbench.benchmark.runs.ranking import work_verdicts

    ratios = paired.verdicts([paired.Ratio("a", 1.0, 1.0, 1.0, 1.0, 10), paired.Ratio("b", 2.0, 2.0, 1.9, 2.1, 10),
                              paired.Ratio("c", 1.05, 1.05, 0.9, 1.2, 10)])
    assert [(r.method, r.verdict) for r in ratios] == [("a", policy.TIE), ("c", policy.TIE), ("b", policy.SLOWER)]
    rows = [{"entry": "a", "cost": 1.0, "cost_low": 0.9, "cost_high": 1.0},
            {"entry": "b", "cost": 2.0, "cost_low": 1.8, "cost_high": 2.0}]
    work_verdicts(rows)
    assert [r["verdict"] for r in rows] == [policy.WINNER, policy.SLOWER]


# ---- statuses (R15, R16): compared and written by their names, never as literals ------------
def test_no_status_is_compared_or_written_as_a_literal():
    """A status word (`integrators.base.Status`, the table-only statuses, the stability map's
    `SKIPPED`) in a comparison, an ``isin``, or as the ``status`` / ``bound`` a row is given, is
    written by its name: a renamed status cannot leave a reader behind."""
    import ast
    from pathlib import Path

    from reelbench.benchmark.studies.stability import SKIPPED
    from reelbench.integrators.base import TABLE_ONLY_STATUSES, Status

    words = {s.value for s in Status} | set(TABLE_ONLY_STATUSES) | {SKIPPED}

    def strings(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return [node.value]
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            return [v for e in node.elts for v in strings(e)]
        return []

    root = Path(__file__).resolve().parents[1] / "benchmark"
    found = []
    for path in sorted(root.rglob("*.py")):
        for n in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(n, ast.Compare):
                values = [v for x in (n.left, *n.comparators) for v in strings(x)]
            elif isinstance(n, ast.keyword) and n.arg in ("status", "bound", "bounded", "high_status"):
                values = strings(n.value)
            elif isinstance(n, ast.Dict):
                values = [v for k, x in zip(n.keys, n.values) if k is not None and strings(k)[:1] in (["status"], ["bound"])
                          for v in strings(x)]
            elif isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "isin":
                values = [v for a in n.args for v in strings(a)]
            else:
                continue
            found += [f"{path.relative_to(root)}:{n.lineno} {v!r}" for v in values if v in words]
    assert found == [], found
