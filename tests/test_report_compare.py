"""`run --compare-with`: the results README says which conclusions changed against an earlier run."""

import pandas as pd

from reelbench.benchmark.studies import runs_report
from reelbench.benchmark.cli.main import main


def _rows(costs: dict) -> pd.DataFrame:
    """One scene, methods with one setting each: (run time, work) given, both targets reached."""
    return pd.DataFrame([{"scene": "s", "integrator": m, "setting": "dt=0.01", "dt": 0.01, "rtol": float("nan"),
                          "t_end": 1.0, "status": "ok", "steps": 100, "run_time": t, "run_time_low": t,
                          "run_time_high": t, "work_evals": w, "energy_error": 1e-6, "position_error_final": 1e-8}
                         for m, (t, w) in costs.items()])


def test_changes_name_the_reproducibility_and_each_speed_up_and_no_verdict():
    before = _rows({"a": (1.0, 1000.0), "b": (7.0, 7000.0)})
    now = pd.concat([_rows({"a": (0.5, 1000.0), "b": (0.7, 7000.0)}), _rows({"c": (0.1, 100.0)})])
    text = runs_report.changes_since(before, now, "the old table")
    assert "## Compared with the old table" in text
    # the two runs both tables have are equal to the last digit; c is in one table only
    assert "2 runs compared: 2 equal to the last digit" in text
    assert "(1 row(s) in only one of the two tables were not compared.)" in text
    assert "| a | 1 | 2× |" in text and "| b | 1 | 10× |" in text
    assert "New in this run: `c`." in text
    # the grid ranks nothing: no verdicts then and now (the answer's is `python -m benchmark answer`)
    assert "Cheapest" not in text and "next `" not in text and "tie of" not in text


def test_an_earlier_table_with_text_in_a_number_column_is_read_as_missing_numbers():
    before = _rows({"a": (1.0, 1000.0)}).astype({"run_time": object, "energy_error": object})
    before.loc[0, "run_time"], before.loc[0, "energy_error"] = "fast", "n/a"
    text = runs_report.changes_since(before, _rows({"a": (0.5, 1000.0)}), "a hand-edited table")
    assert "## Compared with a hand-edited table" in text and "Median speed-up" in text


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


def test_the_sweeps_readme_ranks_nothing_and_names_the_answers_command(tmp_path):
    """The grid sweep's README describes its table (the time per evaluation by implementation,
    the failures) and sends the reader to the main job for which method to use."""
    from reelbench.benchmark.core.report import Provenance

    runs = _sweep_rows().assign(orthogonality_error=1e-12)
    per_eval = runs_report.evaluation_costs(runs).set_index("integrator")
    assert per_eval.loc["dop853", "implementation"] == "scipy-python"
    assert per_eval.loc["dop853", "us_per_eval_median"] == 900.0
    text = runs_report.write_readme(tmp_path, runs, None, provenance=Provenance("python -m benchmark run"),
                                    figures=["work_precision_s.png"]).read_text()
    assert text.startswith("# Grid sweep results")
    assert "`python -m benchmark answer` ->\n`results/README.md`" in text and "ranks nothing" in text
    assert "All 6 runs ok." in text and "| scipy-python | dop853 |" in text
    assert "winner" not in text and " tie" not in text and "cheapest.csv" not in text
    assert "- [work_precision_s.png](work_precision_s.png)" in text


def test_one_load_helper_nan_where_the_platform_does_not_say(monkeypatch):
    """The 1-minute load of a run's row and of every header: NaN where unknown (no getloadavg on
    Windows, or it fails), and the header then says so instead of failing."""
    import math
    import os

    from reelbench.benchmark.core import report
    from reelbench.benchmark.core.report import Provenance

    assert report.one_minute_load() >= 0
    monkeypatch.delattr(os, "getloadavg")
    assert math.isnan(report.one_minute_load())
    assert math.isnan(Provenance("x").load_at_start)
    assert report.load_average(report.one_minute_load()) == "load average unknown"
