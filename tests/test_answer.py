"""The answer study (`benchmark.answer.answer`): cheapest.csv and the answer block from search and
paired-timing rows; end to end on a tiny case, stopped and resumed without losing a row."""

import json

import numpy as np
import pandas as pd
import pytest

from reelbench.benchmark.answer import answer
from reelbench.benchmark.answer.answer_report import answer_block, answer_lines, use_line
from reelbench.benchmark.answer.jobs import timing_jobs
from reelbench.benchmark.answer.table import COLUMNS, answer_table
from reelbench.benchmark.core.policy import LOWER_BOUND


def _search_row(integ, n, metric, target, setting, cost, bound="target", spread=0.08, impl="jax-compiled"):
    return dict(scene="fixed_length", elements=n, integrator=integ, sweep="dt", metric=metric, target=target,
                setting=setting, cost=cost, cost_column="flops", error=target / 2, setting_low=setting,
                setting_high=setting * (1 + spread) if np.isfinite(setting) else np.nan, setting_finer=np.nan,
                high_status="ok", bound=bound, runs=8, spread=spread, implementation=impl, note="")


def _timing_row(n, metric, target, ratios):
    return dict(scene="fixed_length", elements=n, metric=metric, target=target, rounds=ratios[0]["pairs"],
                ratios=json.dumps(ratios), note="")


def _ratio(m, t, r, lo, hi, verdict, pairs=40):
    return dict(method=m, time=t, ratio=r, low=lo, high=hi, pairs=pairs, verdict=verdict)


@pytest.fixture
def tables():
    searched = pd.DataFrame([
        _search_row("lgvi", 10, "energy_error", 1e-4, 0.0088, 1e6),
        _search_row("lie_rk4", 10, "energy_error", 1e-4, 0.0102, 1.3e6),
        _search_row("rk45", 10, "energy_error", 1e-4, np.nan, np.nan, bound="not reached", impl="scipy-python"),
        _search_row("lgvi", 40, "energy_error", 1e-4, 0.002, 9e6),
        _search_row("lie_rk4", 40, "energy_error", 1e-4, 0.0025, 9.5e6),
    ])
    timed = pd.DataFrame([
        _timing_row(10, "energy_error", 1e-4, [_ratio("lgvi", 0.006, 1.0, 1.0, 1.0, "winner"),
                                               _ratio("lie_rk4", 0.01, 1.66, 1.5, 1.8, "slower")]),
        _timing_row(40, "energy_error", 1e-4, [_ratio("lie_rk4", 0.03, 1.0, 1.0, 1.0, "tie"),
                                               _ratio("lgvi", 0.031, 1.02, 0.97, 1.08, "tie")]),
    ])
    return searched, timed


def test_cheapest_csv_has_the_bracket_the_bound_and_the_paired_ratios(tables):
    table = answer_table(*tables)
    assert list(table.columns) == COLUMNS
    work10 = table[(table["elements"] == 10) & (table["cost_kind"] == "work")].set_index("integrator")
    assert work10.loc["lgvi", "verdict"] == "winner" and work10.loc["lie_rk4", "verdict"] == "slower"
    assert work10.loc["rk45", "verdict"] == "not reached"
    assert work10.loc["lgvi", "setting_low"] == 0.0088 and work10.loc["lgvi", "bound"] == "target"
    assert work10.loc["lgvi", "setting_high"] == pytest.approx(0.0088 * 1.08)
    work40 = table[(table["elements"] == 40) & (table["cost_kind"] == "work")].set_index("integrator")
    assert set(work40["verdict"]) == {"tie"}  # 9.0e6 and 9.5e6 overlap within their 10 % brackets
    wall10 = table[(table["elements"] == 10) & (table["cost_kind"] == "wall")].set_index("integrator")
    assert wall10.loc["lie_rk4", "ratio_low"] == 1.5 and wall10.loc["lie_rk4", "pairs"] == 40
    assert wall10.loc["lgvi", "verdict"] == "winner" and wall10.loc["lgvi", "setting"] == "dt=0.0088"
    assert "rk45" not in set(table.loc[table["cost_kind"] == "wall", "integrator"])


def test_a_cost_that_is_not_in_flops_is_never_ranked_by_work(tables):
    """kvaerno5's search has its cost in steps (XLA's cost model does not count its step): 607
    steps is no point on the flops axis, so it is not ranked by work (it would 'win' at 607);
    its wall time is still timed and ranked."""
    searched, timed = tables
    steps = searched.iloc[0].to_dict() | {"integrator": "kvaerno5", "cost": 607.0, "cost_column": "steps",
                                          "sweep": "rtol", "setting": 1e-4}
    searched = pd.concat([searched, pd.DataFrame([steps])], ignore_index=True)
    table = answer_table(searched, timed)
    work10 = table[(table["elements"] == 10) & (table["cost_kind"] == "work")].set_index("integrator")
    assert work10.loc["kvaerno5", "verdict"] == "no flops count" and np.isnan(work10.loc["kvaerno5", "cost"])
    assert "607 steps, not flops" in work10.loc["kvaerno5", "note"]
    assert work10.loc["lgvi", "verdict"] == "winner"
    assert "kvaerno5" in {c[0] for c in timing_jobs(searched)[0].candidates}


def test_a_count_of_evaluations_alone_is_a_lower_bound_and_never_wins(tables):
    """radau's flops count right-hand sides, Jacobians and LU factorisations, not its Newton
    solves: a lower bound. Below the winner's cost it is unranked (and does not make the winner
    a tie); above the winner's interval it is slower, its ratio open above."""
    from reelbench.benchmark.work.flops import counting_rule

    assert counting_rule("radau") == "evaluations" and counting_rule("lgvi") == "step"
    assert counting_rule("tsit5") == "diffrax" and counting_rule("dop853") == "twin"
    searched, timed = tables
    cheap = searched.iloc[0].to_dict() | {"integrator": "radau", "sweep": "rtol", "setting": 1e-3, "cost": 2e5}
    dear = searched.iloc[3].to_dict() | {"integrator": "radau", "sweep": "rtol", "setting": 1e-3, "cost": 3e7}
    table = answer_table(pd.concat([searched, pd.DataFrame([cheap, dear])], ignore_index=True), timed)
    work = table[table["cost_kind"] == "work"].set_index(["elements", "integrator"])
    assert work.loc[(10, "radau"), "verdict"] == LOWER_BOUND and work.loc[(10, "lgvi"), "verdict"] == "winner"
    assert "a lower bound of its work" in work.loc[(10, "radau"), "note"]
    assert work.loc[(40, "radau"), "verdict"] == "slower" and np.isinf(work.loc[(40, "radau"), "ratio_high"])
    assert work.loc[(40, "radau"), "ratio_low"] == pytest.approx(3e7 / 1.08 / 9e6)
    lines = answer_lines(table)
    assert "by work: use `lgvi`" in lines[0] and "radau" not in lines[0]
    block = answer_block(table)
    assert "`radau` by work: its flops leave out its Newton solves, a lower bound (`≥`), never a winner" in block
    # the lower bound shown as such when it is the next method
    only = table[~((table["cost_kind"] == "work") & (table["integrator"] == "lie_rk4"))]
    assert "`radau` at ≥ 3.09× (a lower bound)." in answer_lines(only)[1]


def test_bit_identical_searches_are_ranked_and_timed_once(tables):
    """lgvi_sym's search equal to lgvi's in every twin column: one entry, `lgvi = lgvi_sym`, the
    other row `identical` and not timed; a search differing in its error alone stays apart."""
    searched, timed = tables
    sym = searched.iloc[0].to_dict() | {"integrator": "lgvi_sym"}
    near = searched.iloc[0].to_dict() | {"integrator": "rattle", "error": searched.iloc[0]["error"] * (1 + 1e-15)}
    searched = pd.concat([searched, pd.DataFrame([sym, near])], ignore_index=True)
    [job10, _] = timing_jobs(searched)
    assert {c[0] for c in job10.candidates} == {"lgvi", "lie_rk4", "rattle"}
    table = answer_table(searched, timed)
    work10 = table[(table["elements"] == 10) & (table["cost_kind"] == "work")].set_index("integrator")
    assert work10.loc["lgvi", "entry"] == "lgvi = lgvi_sym" and work10.loc["lgvi_sym", "verdict"] == "identical"
    assert "bit-identical to lgvi's" in work10.loc["lgvi_sym", "note"]
    assert work10.loc["rattle", "entry"] == "rattle" and work10.loc["rattle", "verdict"] == "tie"
    wall10 = table[(table["elements"] == 10) & (table["cost_kind"] == "wall")].set_index("integrator")
    assert wall10.loc["lgvi", "entry"] == "lgvi = lgvi_sym" and "lgvi_sym" not in wall10.index


def test_the_answer_block_says_one_thing_per_scene_and_target(tables):
    lines = answer_lines(answer_table(*tables), {"energy_error": "energy error"})
    assert lines[0].startswith("- **fixed_length**, N = 10, energy error ≤ 0.0001: by wall time: use `lgvi` "
                               "(dt=0.0088, 6 ms, 40 pairs); next `lie_rk4` at 1.66× [1.50–1.80]")
    assert "by wall time: tie: `lie_rk4`" in lines[1] and "`lgvi` at 1.02× [0.97–1.08]" in lines[1]
    assert lines[2] == "  - from N = 10 to N = 40: fastest `lgvi` → `lie_rk4`"


def test_after_a_tie_the_next_method_is_named_as_outside_it():
    """Tie membership goes by the interval, the order by the ratio: after a tie whose wide member
    lies at 1.33x, a narrow 1.18x is "first outside the tie", never "next"."""
    def wall(entry, ratio, low, high, verdict):
        return dict(entry=entry, ratio=ratio, ratio_low=low, ratio_high=high, verdict=verdict, cost=ratio * 1e-3,
                    cost_kind="wall", setting="dt=0.01", pairs=8)

    g = pd.DataFrame([wall("a", 1.0, 1.0, 1.0, "tie"), wall("b", 1.33, 1.05, 1.40, "tie"),
                      wall("c", 1.18, 1.18, 1.22, "slower")])
    line = use_line(g)
    assert line.startswith("tie: `a`") and "`b` at 1.33× [1.05–1.40]" in line
    assert line.endswith("; first outside the tie `c` at 1.18× [1.18–1.22]") and "next" not in line
    won = use_line(g.assign(verdict=["winner", "slower", "slower"]))
    assert won.startswith("use `a`") and won.endswith("; next `c` at 1.18× [1.18–1.22]")


def test_timing_jobs_take_the_compiled_methods_that_met_the_target(tables):
    jobs = timing_jobs(tables[0])
    assert [j.elements for j in jobs] == [10, 40]
    assert jobs[0].candidates == (("lgvi", "dt", 0.0088), ("lie_rk4", "dt", 0.0102))


def test_a_row_digest_survives_the_csv_and_a_changed_row_is_recomputed(tmp_path):
    from reelbench.benchmark.core.store import row_digest
    from reelbench.benchmark.core.study_store import read_rows

    row = _search_row("lgvi", 10, "energy_error", 1e-4, 0.0088, 1e6) | {"job_key": "k1"}
    row["row_digest"] = row_digest(row, answer.NOT_DIGESTED)
    path = tmp_path / "search.csv"
    pd.DataFrame([row]).to_csv(path, index=False)

    def read(log):
        return read_rows(path, answer.SEARCH_IDENTITY, digest=answer.NOT_DIGESTED, log=log)

    assert len(read(lambda m: None)) == 1
    pd.DataFrame([dict(row, cost=1.0)]).to_csv(path, index=False)
    said = []
    assert read(said.append) == [] and "fail their digest" in said[0]


@pytest.mark.slow
def test_the_study_end_to_end_resumes_without_losing_a_row(tmp_path, capsys):
    from reelbench.benchmark.cli.main import main

    args = ["answer", "--scenes", "fixed_length", "--integrators", "lie_rk4,lgvi", "--elements", "2",
            "--t-end", "0.2", "--timing-budget", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    table = pd.read_csv(tmp_path / "cheapest.csv")
    assert set(table["cost_kind"]) == {"work", "wall"}
    assert table["bound"].dropna().isin(["target", "stability", "largest setting", "budget"]).all(), table.to_string()
    first = pd.read_csv(tmp_path / "search.csv")
    capsys.readouterr()
    assert main(args) == 0
    assert "kept 4 of 4 searches" in capsys.readouterr().err
    pd.testing.assert_frame_equal(first, pd.read_csv(tmp_path / "search.csv"))


def test_a_method_on_two_axes_is_two_entries(tables):
    searched = tables[0]
    both = pd.DataFrame([dict(_search_row("tsit5", 10, "energy_error", 1e-4, 0.01, 2e6), sweep="dt"),
                         dict(_search_row("tsit5", 10, "energy_error", 1e-4, 1e-6, 3e6), sweep="rtol")])
    table = answer_table(pd.concat([searched, both]), tables[1].iloc[:0])
    entries = set(table.loc[table["integrator"] == "tsit5", "entry"])
    assert entries == {"tsit5 (fixed dt)", "tsit5 (adaptive)"}
    assert len(timing_jobs(pd.concat([searched, both]))[0].candidates) == 4


def test_a_run_keeps_the_rows_of_other_sizes_and_replaces_its_own():
    base = [_search_row("lgvi", 10, "energy_error", 1e-4, 0.0088, 1e6), _search_row("lgvi", 40, "energy_error", 1e-4, 0.002, 9e6)]
    new = [_search_row("lgvi", 40, "energy_error", 1e-4, 0.0021, 8e6), _search_row("rattle", 40, "energy_error", 1e-4, 0.003, 7e6)]
    from reelbench.benchmark.core.store import merge_rows

    out = merge_rows(base, new, identity=answer.SEARCH_IDENTITY)
    assert [(r["integrator"], r["elements"], r["cost"]) for r in out] == [("lgvi", 10, 1e6), ("lgvi", 40, 8e6),
                                                                          ("rattle", 40, 7e6)]


def test_the_readme_answer_block_is_what_the_main_job_wrote():
    """The project README's block between the answer markers is results/answer.md, as the main job
    (`python -m benchmark answer`, into results/) wrote it: no hand edit, no stale block."""
    from reelbench.benchmark.answer.answer_report import ANSWER_END, ANSWER_START
    from reelbench.benchmark.core.store import ROOT

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = text[text.index(ANSWER_START) + len(ANSWER_START): text.index(ANSWER_END)]
    assert block.strip() == (ROOT / "results" / "answer.md").read_text(encoding="utf-8").strip()


def test_the_searches_run_on_a_dask_cluster_and_the_timing_here(tmp_path):
    """`answer --executor dask`: the searches are tasks of the cluster (one search here), the paired
    timing runs in this process; the table is the same kind as a local run's."""
    distributed = pytest.importorskip("distributed")
    from reelbench.benchmark.cli.main import main

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        rc = main(["answer", "--executor", "dask", "--scheduler", cluster.scheduler_address, "--scenes", "fixed_length",
                   "--integrators", "lie_rk4", "--elements", "2", "--t-end", "0.1", "--targets", "energy_error=1e-4",
                   "--timing-budget", "0.5", "--out", str(tmp_path)])
    assert rc == 0
    searched = pd.read_csv(tmp_path / "search.csv")
    assert len(searched) == 1 and searched["confirmed"].iloc[0] and np.isfinite(searched["setting"].iloc[0])
    table = pd.read_csv(tmp_path / "cheapest.csv")
    assert set(table["cost_kind"]) == {"work", "wall"}
    assert "Generated by `python -m benchmark answer --executor dask" in (tmp_path / "README.md").read_text()


@pytest.mark.parametrize("args, message", [
    (["--executor", "dask"], "--executor dask needs --scheduler"),
    (["--targets", "energy=1e-4"], "'energy' is not a metric"),
    (["--targets", "energy_error=-1"], "must be a positive number"),
    (["--targets", "energy_error=1e-4,energy_error=1e-5"], "each metric at most once"),
])
def test_bad_answer_options_are_refused_before_any_work(tmp_path, capsys, args, message):
    from reelbench.benchmark.cli.main import main

    assert main(["answer", *args, "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_two_answers_agree_on_a_winner_or_on_ties_that_contain_each_others_best(tables):
    from reelbench.benchmark.answer import answer_report

    table = answer_table(*tables)
    same = answer_report.agreement(table, table)
    assert len(same) and same["agree"].all()
    other = table.copy()
    wall10 = (other["elements"] == 10) & (other["cost_kind"] == "wall")
    # the other run: lie_rk4 ahead of lgvi, the two apart (a different winner) -> they disagree
    other.loc[wall10 & (other["integrator"] == "lie_rk4"), ["ratio", "verdict"]] = [1.0, "winner"]
    other.loc[wall10 & (other["integrator"] == "lgvi"), ["ratio", "ratio_low", "verdict"]] = [1.6, 1.5, "slower"]
    a = answer_report.agreement(table, other).set_index(["elements", "cost_kind"])
    assert not a.loc[(10, "wall"), "agree"] and a.loc[(10, "work"), "agree"]
    # a tie that contains the other's winner agrees (and two ties holding each other's best)
    other.loc[wall10 & (other["integrator"] == "lgvi"), ["ratio", "ratio_low", "verdict"]] = [1.04, 0.97, "tie"]
    other.loc[wall10 & (other["integrator"] == "lie_rk4"), "verdict"] = "tie"
    assert answer_report.agreement(table, other).set_index(["elements", "cost_kind"]).loc[(10, "wall"), "agree"]
    assert "1 of 2" not in answer_report.agreement_text(table, table, "itself")


def test_the_main_job_runs_the_default_methods_and_dopri8_and_extended_runs_every_own_method():
    from reelbench.benchmark.answer import answer
    from reelbench.benchmark.runs import sweep

    main = answer.default_methods()
    assert "dopri8" in main and set(main) == set(sweep.default_sweep_names()) | {"dopri8"}
    assert set(answer.default_methods(extended=True)) == set(sweep.default_names())


def test_the_time_accounting_counts_only_the_rows_this_run_made():
    """A resumed run's wall holds only its own work: rows read from an earlier run are left out
    of the solves, the timing and the floor."""
    import json

    import pandas as pd

    from reelbench.benchmark.answer.answer_report import accounting

    def search_row(digest, seconds, setting):
        pts = [{"setting": setting, "status": "ok", "cost": 1.0, "cost_column": "flops", "run_time": seconds,
                "compile_time": 1.0, "other_time": 0.5}]
        return {"scene": "fixed_length", "elements": 10, "integrator": "lgvi", "sweep": "dt",
                "points": json.dumps(pts), "row_digest": digest}

    searched = pd.DataFrame([search_row("old", 100.0, 0.01), search_row("new", 3.0, 0.02)])
    timed = pd.DataFrame([{"seconds": 50.0, "row_digest": "old"}, {"seconds": 2.0, "row_digest": "new"}])
    everything = accounting(searched, timed, 10.0, 1)
    assert "ran 2 solves: 103 s of solving" in everything
    own = accounting(searched, timed, 10.0, 1, kept={"old"})
    assert "ran 1 solves: 3 s of solving, 1 s of compilation" in own and "the paired timing took 2 s" in own
    assert "Floor (solves and compilation over the workers, plus the timing): 6 s" in own
    assert "2 row(s) kept from earlier runs are not counted" in own and "not counted" not in everything
    assert "not counted" not in accounting(searched, timed, 10.0, 1, kept={"elsewhere"})  # none was kept here
    assert accounting(searched.iloc[:1], timed.iloc[:1], 10.0, 1, kept={"old"}).startswith("Time: every search")


@pytest.mark.parametrize("content", [b"scene,elements\nfixed_length,10\nfixed_length,10,3,4\n",
                                     b"\x00\xff garbage \n\x01", b"integrator,cost\nlgvi,1.0\n"])
def test_an_unreadable_earlier_search_table_is_refused_before_any_work_and_left_as_it_was(tmp_path, monkeypatch,
                                                                                           content):
    (tmp_path / "search.csv").write_bytes(content)
    from reelbench.benchmark.core import engine

    monkeypatch.setattr(engine, "run_jobs", lambda *a, **k: pytest.fail("work began"))
    request = answer.AnswerRequest(out=tmp_path, scenes=("fixed_length",), integrators=("lgvi",))
    with pytest.raises(ValueError, match="search.csv.*move it away, or give another --out"):
        answer.run_answer(request, log=lambda m: None)
    assert (tmp_path / "search.csv").read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == ["search.csv"]


def _fake_search(job, cache_dir):
    """A search's row without solving (the runner's stop and resume are under test, not the search)."""
    return dict(_search_row(job.integrator, job.elements, job.metric, job.target, 0.01, 1e6), scene=job.scene,
                sweep=job.sweep, confirmed=True, points="[]", job_time=0.0)


def _fake_timing(job):
    ratios = [_ratio(c[0], 0.01, 1.0, 1.0, 1.0, "tie") for c in job.candidates]
    return dict(scene=job.scene, elements=job.elements, metric=job.metric, target=job.target, ratios=json.dumps(ratios),
                rounds=40, seconds=0.0, note="")


def _stopping(real, stop_at, calls):
    def job(*args, **kwargs):
        if len(calls) == stop_at:
            raise KeyboardInterrupt("signal SIGINT")
        calls.append(args[0])
        return real(*args, **kwargs)
    return job


@pytest.mark.parametrize("stage", ["search", "timing"])
def test_an_answer_stopped_after_its_first_finished_job_keeps_it_and_resumes_from_it(tmp_path, monkeypatch, capsys,
                                                                                      stage):
    """Through the one runner: a stop (KeyboardInterrupt, as the stop handlers raise it) after the
    first finished search, or the first finished timing, keeps every finished row of both tables
    and says so in one line; the same command then keeps them (not run again) and runs the rest."""
    from reelbench.benchmark.answer import jobs
    from reelbench.benchmark.cli.main import main

    searches, timings = [], []
    monkeypatch.setattr(jobs, "references", lambda todo, cache_dir: [])
    monkeypatch.setattr(jobs, "run_search", _stopping(_fake_search, 1 if stage == "search" else None, searches))
    monkeypatch.setattr(jobs, "run_timing", _stopping(_fake_timing, 1 if stage == "timing" else None, timings))
    args = ["answer", "--scenes", "fixed_length", "--integrators", "lgvi,lie_rk4", "--elements", "2", "--targets",
            "energy_error=1e-4,position_error_final=1e-6", "--executor", "serial", "--out", str(tmp_path)]
    assert main(args) == 130
    err = capsys.readouterr().err
    saved = "1 search row(s) and 0 timing row(s)" if stage == "search" else "4 search row(s) and 1 timing row(s)"
    assert f"stopped by Ctrl-C: {saved} are saved in {tmp_path}; run the same command again to resume" in err, err
    first = pd.read_csv(tmp_path / "search.csv")
    assert len(first) == len(searches) and not (tmp_path / "cheapest.csv").exists()
    assert len(pd.read_csv(tmp_path / "timing.csv")) if stage == "timing" else not (tmp_path / "timing.csv").exists()

    done = len(searches), len(timings)
    monkeypatch.setattr(jobs, "run_search", _stopping(_fake_search, None, searches))
    monkeypatch.setattr(jobs, "run_timing", _stopping(_fake_timing, None, timings))
    assert main(args) == 0
    err = capsys.readouterr().err
    assert f"kept {done[0]} of 4 searches" in err and len(searches) == 4, err
    assert (f"kept {done[1]} of 2 paired timings" in err) == (stage == "timing") and len(timings) == 2
    after = pd.read_csv(tmp_path / "search.csv")
    pd.testing.assert_frame_equal(first, after.iloc[:len(first)])  # the kept rows, as they were
    assert len(after) == 4 and len(pd.read_csv(tmp_path / "timing.csv")) == 2
    assert set(pd.read_csv(tmp_path / "cheapest.csv")["cost_kind"]) == {"work", "wall"}
