"""`run --compare-with`: the results README says which conclusions changed against an earlier run."""

import pandas as pd

from benchmark import runs_report
from benchmark.cli import main


def _rows(times: dict) -> pd.DataFrame:
    """One scene, two methods, one setting each: run times given, both reach both targets."""
    return pd.DataFrame([{"scene": "s", "integrator": m, "setting": "dt=0.01", "status": "ok", "run_time": t,
                          "energy_error": 1e-6, "position_error_final": 1e-8} for m, t in times.items()])


def test_changes_name_the_winners_then_and_now_and_each_speed_up():
    before = _rows({"a": 1.0, "b": 7.0})
    now = pd.concat([_rows({"a": 0.5, "b": 0.7}), _rows({"c": 0.1})])
    text = runs_report.changes_since(before, now, "the old table")
    assert "## Compared with the old table" in text
    row = next(line for line in text.splitlines() if line.startswith("| s |"))
    # then: a was 7x cheaper than b; now c wins, and b / a has shrunk to 1.4x
    assert "`a` (dt=0.01, 1 s), 7× cheaper than `b`" in row and "`c` (dt=0.01, 0.1 s)" in row
    assert "`b` / `a` = 1.4× (then 7×)" in row
    assert "| a | 1 | 2× |" in text and "| b | 1 | 10× |" in text
    assert "New in this run: `c`." in text


def test_compare_with_a_file_that_is_not_a_runs_table_is_refused(tmp_path, capsys):
    bad = tmp_path / "x.csv"
    bad.write_text("a,b\n1,2\n")
    assert main(["run", "--compare-with", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--compare-with" in err and "no column(s)" in err
    assert main(["run", "--compare-with", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "o")]) == 2
