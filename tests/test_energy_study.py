"""The energy study (benchmark/studies/horizon.py, a study of `benchmark.core.study.run`): it runs on
the scenes it is given, at both sizes and both settings, and merges into energy_horizon.csv: a
rerun keeps the histories it does not recompute (other methods, scenes, sizes) and reuses those it
would recompute identically."""

import pandas as pd

from reelbench.benchmark.core import study
from reelbench.benchmark.studies import grid, horizon, horizon_report
from reelbench.benchmark.runs.sweep import MethodSettings


def run_horizon_study(t_end, out, overrides=(), jobs=None, log=None, selected=None, scenes=None, failed=None):
    """The energy study on the runner, and the figures it lists (as `run --horizon` does)."""
    the_study = horizon.study(t_end, scenes, overrides=overrides, selected=selected, workers=jobs)
    study.run(the_study, out, command="test", log=log, failed=failed)
    return horizon_report.listed(out, {j.tabled_as for j in the_study.jobs})


def test_the_study_runs_on_the_fixed_length_scenes_it_is_given():
    said = []
    assert horizon.energy_scenes(["deployment", "fixed_length", "retrieval"], log=said.append) == ["fixed_length"]
    assert "deployment, retrieval left out of the energy study" in said[0]
    assert horizon.energy_scenes(["deployment"], log=said.append) == []


def test_the_plan_runs_what_it_lists():
    plan = horizon.runs(["lgvi", "lgvi_suzuki4", "dopri8"])
    assert {(v, n, m.name, horizon.setting_of(m)) for v, n, m in plan} == {
        *(("", n, "lgvi", s) for n in horizon.ELEMENTS for s in ("dt=0.005", "dt=0.0025")),
        *(("", 10, "lgvi_suzuki4", s) for s in ("dt=0.005", "dt=0.0025")),
        *(("", n, "dopri8", "rtol=1e-08, atol=1e-10") for n in horizon.ELEMENTS),
        *(("slack", 10, "lgvi", s) for s in ("dt=0.005", "dt=0.0025")),
        ("slack", 10, "lgvi_suzuki4", "dt=0.005"), ("slack", 10, "dopri8", "rtol=1e-08, atol=1e-10")}
    # the compositions declare no settings of their own: they get the LGVI's step
    assert horizon.declared("lgvi_yoshida4").settings == {"dt": horizon.COMPOSITION_STEP}
    assert {(v, n) for v, n, _ in horizon.runs(["lgvi"], elements=(4,), variants=("",))} == {("", 4)}
    assert horizon.finer(MethodSettings("x", {"dt": 0.01})).settings == {"dt": 0.005}


def test_the_slack_variant_adds_the_effect_and_names_its_table_scene():
    from reelbench.models import load_scene

    scene = load_scene("fixed_length")
    assert horizon.variant_overrides(scene, "") == ()
    (key, effects), = horizon.variant_overrides(scene, "slack")
    assert key == "effects" and load_scene("fixed_length", effects=list(effects)).has("slack")
    assert horizon.table_scene("fixed_length", "slack") == "fixed_length_slack"


def test_a_rerun_merges_into_the_table_and_keeps_what_it_did_not_recompute(tmp_path):
    def history(name):
        return pd.DataFrame({"t": [0.0, 0.1, 0.2], "energy_error": [0.0, 1e-9, 2e-9], "tension_min": 1.0,
                             "method": f"{name} rtol=1e-08, atol=1e-10 N=10", "integrator": name, "scene": "fixed_length",
                             "elements": 10, "setting": "rtol=1e-08, atol=1e-10", "status": "ok", "t_end": 0.2,
                             "job_key": "from-an-earlier-run"})

    # dopri8's is a run of the study (kept); rk45 is not in its plan: its history is of a run the
    # study does not make, and is dropped
    assert "rk45" not in {m.name for m in horizon.methods()}
    pd.concat([history("dopri8"), history("rk45")]).to_csv(tmp_path / "energy_horizon.csv", index=False)
    said = []
    one_size = (("elements", 4),)  # --set elements=4: that size only (one compilation per setting)
    figures = run_horizon_study(0.2, tmp_path, one_size, jobs=0, log=said.append, selected=["lgvi"],
                                scenes=["fixed_length"])
    table = pd.read_csv(tmp_path / "energy_horizon.csv")
    assert figures == [("energy_horizon_fixed_length.png", "")] and (tmp_path / figures[0][0]).is_file()
    runs = table.groupby(list(horizon.RUN_KEY)).size()
    assert len(runs) == 3 and runs[("fixed_length", 10, "dopri8", "rtol=1e-08, atol=1e-10")] == 3  # kept as it was
    assert "rk45" not in set(table["integrator"])
    assert set(table.loc[table.integrator == "lgvi", "setting"]) == {"dt=0.005", "dt=0.0025"}
    lgvi = table[table.integrator == "lgvi"]
    assert lgvi[["tension_min", "energy_dev", "axial_P", "axial_P4"]].notna().all().all()
    assert (lgvi["axial_P"] > 0).all() and (lgvi["energy_error"] >= lgvi["energy_dev"].abs() - 1e-15).all()  # block max, mean
    said.clear()
    run_horizon_study(0.2, tmp_path, one_size, jobs=0, log=said.append, selected=["lgvi"], scenes=["fixed_length"])
    assert any("kept 2 of 2 runs" in line for line in said)
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "energy_horizon.csv"), table)


def test_bad_input_is_refused_before_any_work(tmp_path, capsys):
    from reelbench.benchmark.cli.main import main

    assert main(["energy", "--integrators", "no_such_method", "--out", str(tmp_path / "e")]) == 2
    assert capsys.readouterr().err.startswith("error:") and not (tmp_path / "e").exists()
    assert main(["energy", "--horizon", "0", "--out", str(tmp_path / "e")]) == 2
    assert main(["energy", "--variants", "plain,stiff", "--out", str(tmp_path / "e")]) == 2
    assert "unknown string variant(s) stiff" in capsys.readouterr().err and not (tmp_path / "e").exists()


def test_run_makes_the_energy_study_only_when_given_a_horizon(tmp_path, monkeypatch, capsys):
    """The study is its own command (`energy`); `run` makes it too only with --horizon T, and
    only then checks its size (a horizon far too long is refused before any work)."""
    from reelbench.benchmark.cli.main import main

    seen = []
    monkeypatch.setattr(grid, "run_sweep", lambda request, log: seen.append(request) or 0)
    run = ["run", "--quick", "--scenes", "fixed_length", "--integrators", "lgvi", "--out", str(tmp_path / "o")]
    assert main(run) == 0 and main([*run, "--horizon", "5"]) == 0 and main([*run, "--horizon", "0"]) == 0
    assert [r.energy_horizon for r in seen] == [0.0, 5.0, 0.0]
    assert main([*run, "--horizon", "1e9"]) == 2 and "--horizon 1e+09" in capsys.readouterr().err
    assert len(seen) == 3


def test_the_energy_command_rewrites_only_its_section_of_the_readme(tmp_path):
    from reelbench.benchmark.studies.properties import SECTION, write_energy_section

    t = [0.0, 10.0, 20.0]
    pd.DataFrame({"t": t, "energy_error": [0.0, 1e-9, 2e-9], "energy_dev": [0.0, -1e-9, -2e-9], "axial_P": 1.0,
                  "tension_min": 1.0, "method": "lgvi dt=0.005 N=10", "integrator": "lgvi", "scene": "fixed_length",
                  "elements": 10, "setting": "dt=0.005", "status": "ok"}).to_csv(tmp_path / "energy_horizon.csv",
                                                                                  index=False)
    assert write_energy_section(tmp_path) == tmp_path / "energy_horizon.md"  # no README: the section alone
    (tmp_path / "README.md").write_text("# Results\nHorizons — sweep: 10 s; energy study: 100 s.\n\n## Before\nkept\n\n"
                                        f"{SECTION}\nold words\n\n## After\nkept too\n")
    assert write_energy_section(tmp_path) == tmp_path / "README.md"
    text = (tmp_path / "README.md").read_text()
    assert "old words" not in text and "## Before\nkept" in text and "## After\nkept too" in text
    assert "energy study: 20 s." in text and text.count(SECTION) == 1 and "`lgvi` N=10 dt=0.005" in text


# ------------------------------------------------------------------------------------------
# On the one runner: stop, resume, a dead worker, --fresh, an earlier table of older code
# ------------------------------------------------------------------------------------------
def _history_row(job):
    """A stand-in for `horizon.run_job` (the runner is under test, not the physics)."""
    t = [float(k) for k in range(21)]
    history = pd.DataFrame({"t": t, "energy_error": [1e-9 * k for k in range(21)],
                            "energy_dev": [-1e-9 * k for k in range(21)], "axial_P": 1.0, "tension_min": 1.0})
    return {**horizon._run_columns(job), "label": horizon.label(job.scene, job.elements, job.method), "status": "ok",
            "history": history}


def _lgvi_at_n4(**kw):
    """The LGVI's two runs at N = 4 on fixed_length, 20 s, in this process."""
    return horizon.study(20.0, ["fixed_length"], overrides=(("elements", 4),), selected=["lgvi"], workers=0, **kw)


def _no_figure(monkeypatch):
    from pathlib import Path

    def draw(g, scene, out):
        path = Path(out) / f"energy_horizon_{scene}.png"
        path.write_bytes(b"")
        return path

    monkeypatch.setattr(horizon_report, "energy_horizon", draw)


def test_a_stopped_study_keeps_its_finished_runs_and_a_rerun_computes_the_rest(tmp_path, monkeypatch):
    _no_figure(monkeypatch)
    calls = []

    def stop_at_the_second(job):
        if calls:
            raise KeyboardInterrupt("signal SIGINT")
        calls.append(job)
        return _history_row(job)

    monkeypatch.setattr(horizon, "run_job", stop_at_the_second)
    said = []
    assert study.run(_lgvi_at_n4(), tmp_path, command="test", log=said.append) == 130
    table = pd.read_csv(tmp_path / "energy_horizon.csv")
    assert table["setting"].nunique() == 1 and len(table) == 21 and table["job_key"].notna().all()  # the first run
    assert said[-1].startswith("stopped by") and (tmp_path / "energy_horizon_fixed_length.png").is_file()
    monkeypatch.setattr(horizon, "run_job", _history_row)
    said.clear()
    assert study.run(_lgvi_at_n4(), tmp_path, command="test", log=said.append) == 0
    assert any("kept 1 of 2 runs" in line for line in said), said
    table = pd.read_csv(tmp_path / "energy_horizon.csv")
    assert table.groupby("setting").size().to_dict() == {"dt=0.0025": 21, "dt=0.005": 21}
    recomputed = []
    monkeypatch.setattr(horizon, "run_job", lambda job: recomputed.append(job) or _history_row(job))
    assert study.run(_lgvi_at_n4(), tmp_path, command="test", fresh=True, log=said.append) == 0
    assert len(recomputed) == 2  # --fresh recomputes the runs in the table


def test_a_run_whose_worker_died_is_left_out_and_the_energy_command_fails(tmp_path, monkeypatch, capsys):
    from reelbench.benchmark.cli.main import main

    _no_figure(monkeypatch)

    def dies_at_the_finer_step(job):
        if horizon.setting_of(job.method) == "dt=0.0025" and job.elements == 4:
            return horizon.crash_row(job, MemoryError("out of memory"))
        return _history_row(job)

    monkeypatch.setattr(horizon, "run_job", dies_at_the_finer_step)
    # the dying run's earlier history (another horizon) is not drawn from stale rows
    stale = _history_row(horizon.Job("fixed_length", 4, MethodSettings("lgvi", {"dt": 0.0025}), 10.0, ()))
    pd.DataFrame(horizon.expand(stale)).assign(job_key="older").to_csv(
        tmp_path / "energy_horizon.csv", index=False)
    rc = main(["energy", "--integrators", "lgvi", "--variants", "plain", "--horizon", "20", "--jobs", "0",
               "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 1, err
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: horizon: 1 of 4 runs did not finish: lgvi dt=0.0025 N=4 on fixed_length "
                           "(MemoryError: out of memory)"), err
    table = pd.read_csv(tmp_path / "energy_horizon.csv")
    assert set(zip(table["elements"], table["setting"])) == {(4, "dt=0.005"), (10, "dt=0.005"), (10, "dt=0.0025")}
    assert (tmp_path / "energy_horizon.md").is_file()  # the text is written from the runs that finished

    failed = []
    assert study.run(_lgvi_at_n4(), tmp_path, command="test", log=lambda s: None, failed=failed) == 1
    assert failed == ["lgvi dt=0.0025 N=4 on fixed_length (MemoryError: out of memory)"]


def test_an_earlier_table_of_older_code_is_read_with_its_columns_filled(tmp_path, monkeypatch):
    """A table from before the study had sizes and scenes (`horizon.read_earlier`, the runner's
    `Study.read_earlier`): its runs get fixed_length and N = 10 and are kept beside this run's."""
    _no_figure(monkeypatch)
    monkeypatch.setattr(horizon, "run_job", _history_row)
    pd.DataFrame({"t": [0.0, 1.0], "energy_error": [0.0, 1e-9], "method": "lgvi dt=0.005"}).to_csv(
        tmp_path / "energy_horizon.csv", index=False)
    assert study.run(_lgvi_at_n4(), tmp_path, command="test", log=lambda s: None) == 0
    table = pd.read_csv(tmp_path / "energy_horizon.csv")
    old = table[table["elements"] == 10]
    assert len(old) == 2 and set(old["scene"]) == {"fixed_length"} and set(old["integrator"]) == {"lgvi"}
    assert set(old["setting"]) == {"dt=0.005"} and set(table.loc[table["elements"] == 4, "setting"]) == {
        "dt=0.005", "dt=0.0025"}


def test_a_study_run_inside_another_leaves_the_lock_and_the_stop_to_it(tmp_path, monkeypatch):
    """`run --horizon`: the sweep holds its output's lock; the energy study saves each run and
    a stop reaches the sweep (`study.run(..., held=True)`)."""
    import dataclasses

    import pytest

    _no_figure(monkeypatch)
    steps = []
    monkeypatch.setattr(horizon, "run_job", lambda job: steps.append("job") or _history_row(job))
    the_study = dataclasses.replace(_lgvi_at_n4(), after_jobs=lambda out, log: steps.append("after"),
                                    report=lambda out, rows, provenance: steps.append("report") or "")
    with study.exclusive(tmp_path, log=lambda s: None):
        assert study.run(the_study, tmp_path, command="test", log=lambda s: None, held=True) == 0
    assert steps == ["job", "job", "after", "report"]

    def stop(job):
        raise KeyboardInterrupt("signal SIGINT")

    steps.clear()
    monkeypatch.setattr(horizon, "run_job", stop)
    the_study = dataclasses.replace(the_study, run_job=stop)
    with pytest.raises(KeyboardInterrupt):
        study.run(the_study, tmp_path, command="test", log=lambda s: None, fresh=True, held=True)
    assert steps == []  # neither the step after the jobs nor the report of a stopped study inside another
    assert len(pd.read_csv(tmp_path / "energy_horizon.csv")) == 42  # the runs saved before are kept
