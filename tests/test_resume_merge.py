"""End to end, in this process: a run restricted to other methods keeps the rows already in its
--out and writes its files from the merged table; rows edited by hand are named and recomputed;
a resume with nothing to compute recomputes nothing; a run that would mix horizons is refused.

The sweeps are tiny (fixed_length with one element, 0.04 s, serial executor)."""

import pandas as pd
import pytest

from reelbench.benchmark.cli.main import main

TINY = ["--scenes", "fixed_length", "--t-end", "0.04", "--set", "elements=1", "--executor", "serial", "--repeats",
        "1", "--horizon", "0.1", "--jobs", "1"]
LGVI = ["run", "--integrators", "lgvi", "--dts", "0.01,0.005", *TINY]
RK45 = ["run", "--integrators", "rk45", "--rtols", "1e-4", *TINY]


def _run(args, out, capsys) -> tuple[int, str]:
    rc = main([*args, "--out", str(out)])
    return rc, capsys.readouterr().err


def _rows(out) -> pd.DataFrame:
    return pd.read_csv(out / "runs.csv").set_index("setting")


def test_a_restricted_run_keeps_the_other_rows_and_a_resume_trusts_only_checked_rows(tmp_path, capsys):
    out = tmp_path / "out"
    rc, err = _run(LGVI, out, capsys)
    assert rc == 0, err
    first = _rows(out)
    assert list(first.index) == ["dt=0.01", "dt=0.005"] and first["row_digest"].notna().all()
    assert {"run_time_low", "run_time_high", "timing_repeats", "load_avg", "us_per_eval"} <= set(first.columns)

    # another method into the same --out: added, the LGVI rows kept as they were
    rc, err = _run(RK45, out, capsys)
    assert rc == 0, err
    assert "this run writes 1 row(s) of 1 scene(s) (0 replacing rows there, 1 new) and keeps the other 2" in err, err
    both = _rows(out)
    assert list(both.index) == ["dt=0.01", "dt=0.005", "rtol=0.0001"]
    pd.testing.assert_frame_equal(both.loc[first.index, first.columns], first, check_dtype=False)
    readme = (out / "README.md").read_text()
    assert "`rk45`" in readme and "`lgvi`" in readme and "the other 2 come from earlier runs" in readme
    assert not (out / "cheapest.csv").exists()  # the grid ranks nothing: the answer is `answer`'s
    energy = pd.read_csv(out / "energy_horizon.csv")
    # rk45 is not in the energy study's plan (`horizon.PLAN`): the LGVI's history is kept
    assert set(energy["integrator"]) == {"lgvi"}

    # hand edits: a plausible error, a text where a time belongs; both are named and recomputed
    table = pd.read_csv(out / "runs.csv")
    table["run_time"] = table["run_time"].astype(object)
    table.loc[0, "energy_error"] = 1e-20
    table.loc[1, "run_time"] = "fast"
    table.to_csv(out / "runs.csv", index=False)
    rc, err = _run(LGVI, out, capsys)
    assert rc == 0, err
    assert "row fixed_length/lgvi/dt=0.01 is not trusted (its values do not match the digest" in err, err
    assert "row fixed_length/lgvi/dt=0.005 is not trusted (run_time = 'fast' is not a number)" in err, err
    assert "resuming" not in err  # neither edited row was kept
    again = _rows(out)
    assert again.loc["dt=0.01", "energy_error"] == first.loc["dt=0.01", "energy_error"]  # recomputed: the same physics
    assert pd.api.types.is_float_dtype(again["run_time"])
    assert again.loc["rtol=0.0001", "row_digest"] == both.loc["rtol=0.0001", "row_digest"]  # rk45 untouched
    assert "horizon: kept 2 of 2 runs" in err  # the energy study of unchanged inputs is not recomputed

    # nothing to compute: nothing is recomputed, no figure redrawn
    rc, err = _run(LGVI, out, capsys)
    assert rc == 0, err
    assert "resuming: 2 of 2 runs already done" in err
    assert "figure: work_precision_fixed_length.png kept" in err and "figure: paper_fixed_length.png kept" in err
    assert "solving" not in err and "horizon: kept 2 of 2 runs" in err and "to t = 0.1 s ..." not in err


def test_a_run_that_would_mix_two_horizons_in_one_table_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    rc, err = _run([*RK45, "--no-figures"], out, capsys)
    assert rc == 0, err
    before = (out / "runs.csv").read_bytes()
    longer = [a if a != "0.04" else "0.08" for a in RK45]
    rc, err = _run(longer, out, capsys)
    assert rc == 2 and err.startswith("error:"), err
    assert "scene 'fixed_length': its 1 rows there are over t_end = 0.04 s, this run's over 0.08 s" in err
    assert "give another --out" in err and "run_time" not in err
    assert (out / "runs.csv").read_bytes() == before


def test_a_run_other_than_the_default_sweep_needs_an_explicit_out(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--quick"]) == 2
    err = capsys.readouterr().err
    assert "not the default sweep (--quick)" in err and "--out results/grid" in err
    assert not (tmp_path / "results").exists()


def test_the_committed_grid_cites_the_other_studies_where_they_write_by_default(tmp_path):
    """results/grid/ is the grid sweep's; the orders, stability and energy studies write into
    results/ by default, and the grid's README cites them there unless its own directory has them."""
    from reelbench.benchmark.studies import grid

    committed = grid.COMMITTED_RESULTS
    assert committed == grid.store.ROOT / "results" / "grid" and grid.is_committed_results(committed)
    assert grid.study_file(committed, "orders.csv") == committed.parent / "orders.csv"
    assert grid.study_file(committed, "stability/stability.csv") == committed.parent / "stability" / "stability.csv"
    assert grid.study_file(committed, "runs.csv") == committed / "runs.csv"  # its own, where it is
    assert grid.study_file(tmp_path, "orders.csv") == tmp_path / "orders.csv"  # any other --out: its own


@pytest.mark.parametrize("text, wrote", [
    ("# x\n\n<!-- answer:start -->\nold\n<!-- answer:end -->\n\nrest\n", True),
    ("# x\nno markers\n", False),
    ("<!-- answer:end -->\n<!-- answer:start -->\n", False),
])
def test_the_answer_block_replaces_only_the_text_between_its_markers(tmp_path, text, wrote):
    from reelbench.benchmark.answer.answer_report import write_answer

    readme = tmp_path / "README.md"
    readme.write_text(text)
    said = write_answer(readme, "- one\n- two\n")
    if wrote:
        assert readme.read_text() == "# x\n\n<!-- answer:start -->\n- one\n- two\n<!-- answer:end -->\n\nrest\n"
        assert "rewritten" in said
    else:
        assert readme.read_text() == text and "was not written" in said


def test_an_untrusted_row_outside_the_run_is_set_aside_not_lost(tmp_path, capsys):
    out = tmp_path / "out"
    quiet = ["--no-figures"]
    rc, err = _run([*RK45, *quiet], out, capsys)
    assert rc == 0, err
    table = pd.read_csv(out / "runs.csv")
    table["run_time"] = table["run_time"].astype(object)
    table.loc[0, "run_time"] = "n/a"
    table.to_csv(out / "runs.csv", index=False)
    rc, err = _run([*LGVI, *quiet], out, capsys)
    assert rc == 0, err
    assert "1 untrusted row(s) of" in err and "moved to" in err and "fixed_length/rk45/rtol=0.0001" in err, err
    assert list(_rows(out).index) == ["dt=0.01", "dt=0.005"]  # the table holds trusted rows only
    aside = pd.read_csv(out / "runs.rejected.csv")
    assert list(aside["setting"]) == ["rtol=0.0001"] and "is not a number" in aside["rejected_because"].iloc[0]
