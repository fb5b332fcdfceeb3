"""The cliff status: a run that finished with an error beyond a sanity bound is "inaccurate",
not "ok", keeps no accuracy values and is a status the runs table knows."""

import numpy as np
import pytest

from reelbench.benchmark.runs import metrics
from reelbench.benchmark.runs import runner
from reelbench.benchmark.runs import table
from reelbench.benchmark.runs.sweep import Task
from reelbench.models import load_scene


def test_the_sanity_bounds_are_a_tenth_of_the_energy_scale_and_a_hundredth_of_the_string():
    bounds = metrics.sanity_bounds(load_scene("fixed_length"))  # 10 m deployed
    assert bounds == {"energy_error": 0.1, "position_error_max": pytest.approx(0.1)}
    assert metrics.sanity_bounds(load_scene("retrieval"))["position_error_max"] == pytest.approx(0.15)


@pytest.mark.parametrize("values, broken", [
    # dopri5 at dt = 10 ms on fixed_length in the committed table before this status
    ({"energy_error": 1.175, "position_error_max": 13.9}, ["energy_error 1.18 > 0.1", "position_error_max 13.9 > 0.1"]),
    ({"energy_error": 0.153, "position_error_max": 0.0023}, ["energy_error 0.153 > 0.1"]),  # dopri8 at 20 ms
    ({"energy_error": 0.05, "position_error_max": 0.2}, ["position_error_max 0.2 > 0.1"]),
    ({"energy_error": 0.1, "position_error_max": 0.1}, []),  # on the bound: still a solution
    ({"energy_error": 1e-3, "position_error_max": np.nan}, []),  # no reference: only energy can break
])
def test_a_run_beyond_either_bound_is_no_solution_and_says_which(values, broken):
    reason = metrics.inaccurate_reason(values, load_scene("fixed_length"))
    assert all(b in reason for b in broken) and (reason == "") == (not broken)


def test_inaccurate_is_a_status_of_the_runs_table_and_its_rows_hold_no_accuracy():
    assert metrics.INACCURATE in table.statuses()
    row = {"scene": "s", "integrator": "i", "setting": "dt=0.01", "status": metrics.INACCURATE, "run_time": 1.0,
           **{m: np.nan for m in metrics.ACCURACY}}
    assert table.check_row(row) is None
    assert table.check_row({**row, "energy_error": 1.2}) is not None  # only a solution has accuracy values


def test_the_runner_marks_a_finished_run_beyond_a_bound_inaccurate(monkeypatch):
    task = Task("fixed_length", "lgvi", dt=0.01, t_end=0.2, overrides=(("elements", 2),))
    ok = runner.finish_row(runner.run_task(task, repeats=0, reference=False), "k")
    assert ok["status"] == "ok" and 0 < ok["energy_error"] < metrics.ENERGY_SANITY_BOUND
    # the same run against a bound below its own energy error: finished, but no solution
    monkeypatch.setattr(metrics, "ENERGY_SANITY_BOUND", ok["energy_error"] / 2)
    bad = runner.finish_row(runner.run_task(task, repeats=0, reference=False), "k")
    assert bad["status"] == metrics.INACCURATE and "energy_error" in bad["reason"]
    assert all(np.isnan(bad[m]) for m in metrics.ACCURACY) and bad["steps"] == ok["steps"]
    assert table.check_row(bad) is None
