"""`run --compare-with`: the results README says which conclusions changed against an earlier run."""

import pandas as pd

from benchmark import runs_report
from benchmark.cli import main


def _rows(costs: dict) -> pd.DataFrame:
    """One scene, methods with one setting each: (run time, work) given, both targets reached."""
    return pd.DataFrame([{"scene": "s", "integrator": m, "setting": "dt=0.01", "dt": 0.01, "rtol": float("nan"),
                          "t_end": 1.0, "status": "ok", "steps": 100, "run_time": t, "run_time_low": t,
                          "run_time_high": t, "work_evals": w, "energy_error": 1e-6, "position_error_final": 1e-8}
                         for m, (t, w) in costs.items()])


def test_changes_name_the_verdicts_then_and_now_the_reproducibility_and_each_speed_up():
    before = _rows({"a": (1.0, 1000.0), "b": (7.0, 7000.0)})
    now = pd.concat([_rows({"a": (0.5, 1000.0), "b": (0.7, 7000.0)}), _rows({"c": (0.1, 100.0)})])
    text = runs_report.changes_since(before, now, "the old table")
    assert "## Compared with the old table" in text
    # the two runs both tables have are equal to the last digit; c is in one table only
    assert "2 runs compared: 2 equal to the last digit" in text
    assert "(1 row(s) in only one of the two tables were not compared.)" in text
    row = next(line for line in text.splitlines() if line.startswith("| s | energy error"))
    # then: a won by work, 7x below b; now c wins, 10x below a (ratios with their ranges)
    assert "| `a`, next `b` 7.00× (" in row and "| `c`, next `a` 10× (9.09×–11×) |" in row, row
    assert "| a | 1 | 2× |" in text and "| b | 1 | 10× |" in text
    assert "New in this run: `c`." in text


def test_a_close_call_is_a_tie_in_the_comparison():
    before = _rows({"a": (1.0, 1000.0), "b": (1.0, 1050.0)})
    text = runs_report.changes_since(before, before, "itself")
    row = next(line for line in text.splitlines() if line.startswith("| s | energy error"))
    assert row.count("tie of `a`, `b`") == 2, row


def test_the_comparison_ranks_then_and_now_in_one_unit():
    """flops where both tables have them; else the sum of counts in both, never one unit against another."""
    before = _rows({"a": (1.0, 1000.0), "b": (1.0, 3000.0)})
    now = before.assign(flops=before["integrator"].map({"a": 9e6, "b": 1e6}))  # by flops, b is cheaper
    mixed = runs_report.changes_since(before, now, "a table without flops")
    row = next(line for line in mixed.splitlines() if line.startswith("| s | energy error"))
    assert "(work_evals, the count both tables have)" in mixed and row.count("`a`, next `b` 3.00×") == 2, row
    both = runs_report.changes_since(now, now, "itself")
    row = next(line for line in both.splitlines() if line.startswith("| s | energy error"))
    assert "(flops, the count both tables have)" in both and row.count("`b`, next `a` 9.00×") == 2, row


def test_compare_with_a_file_that_is_not_a_runs_table_is_refused(tmp_path, capsys):
    bad = tmp_path / "x.csv"
    bad.write_text("a,b\n1,2\n")
    assert main(["run", "--compare-with", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--compare-with" in err and "no column(s)" in err
    assert main(["run", "--compare-with", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "o")]) == 2


def _sweep_rows() -> pd.DataFrame:
    """Two compiled methods and a scipy one: the scipy method has the least work, the most time."""
    rows = []
    for name, impl, t, w in (("lgvi", "jax-compiled", 0.01, 3000.0), ("tsit5", "jax-compiled", 0.05, 2000.0),
                             ("dop853", "scipy-python", 0.9, 1000.0)):
        for k, f in enumerate((1.0, 2.0)):
            rows.append({"scene": "s", "integrator": name, "setting": f"dt={0.01 / f:g}", "dt": 0.01 / f,
                         "rtol": float("nan"), "t_end": 1.0, "status": "ok", "steps": 100 * f, "run_time": t * f,
                         "run_time_low": t * f, "run_time_high": t * f, "work_evals": w * f,
                         "energy_error": 1e-3 / 4 ** (k + 1), "position_error_final": 1e-5 / 4 ** (k + 1),
                         "implementation": impl, "us_per_eval": 1e6 * t / w})
    return pd.DataFrame(rows)


def test_the_sweep_ranks_every_method_by_work_and_leaves_wall_time_to_paired_timing():
    """A sweep's single solves give no wall-time verdict (lgvi's 5x lead here would have been a
    winner under the old factor-2 rule): its cheapest.csv holds work rows only, and the report
    and the answer block send the reader to `answer`'s paired timing."""
    runs = _sweep_rows()
    table = runs_report.cheapest_table(runs)
    assert set(table["cost_kind"]) == {"work"} and set(table["integrator"]) == {"lgvi", "tsit5", "dop853"}
    assert set(table.loc[table["verdict"] == "winner", "integrator"]) == {"dop853"}
    text = runs_report.answers(runs, table)
    assert "### By wall time\n\nBy wall time: no verdict from the sweep's single solves" in text
    assert "python -m benchmark answer" in text and "Never ranked by wall time: `dop853`" in text
    assert "### By work, among every method, read off the step grid" in text
    per_eval = runs_report.evaluation_costs(runs).set_index("integrator")
    assert per_eval.loc["dop853", "implementation"] == "scipy-python"
    assert per_eval.loc["dop853", "us_per_eval_median"] == 900.0
    block = runs_report.answer_block(runs, table, "All 6 runs ok.")
    lines = block.strip().splitlines()
    assert len(lines) == 5 and lines[3] == "- All 6 runs ok."
    assert "by work, off the step grid: s `dop853`" in lines[0] and "wall time" not in lines[0]
    assert "no verdict from the sweep's single solves" in lines[2] and "python -m benchmark answer" in lines[2]
