"""The energy study (benchmark/horizon.py, `pipelines.run_horizon_study`): it runs on the scenes
it is given, at both sizes and both settings, and merges into energy_horizon.csv: a rerun keeps
the histories it does not recompute (other methods, scenes, sizes) and reuses those it would
recompute identically."""

import pandas as pd

from benchmark import horizon, pipelines
from benchmark.sweep import MethodSettings


def test_the_study_runs_on_the_fixed_length_scenes_it_is_given():
    said = []
    assert pipelines.energy_scenes(["deployment", "fixed_length", "retrieval"], log=said.append) == ["fixed_length"]
    assert "deployment, retrieval left out of the energy study" in said[0]
    assert pipelines.energy_scenes(["deployment"], log=said.append) == []


def test_every_method_runs_at_two_sizes_and_two_settings():
    plan = horizon.runs(["lgvi", "tsit5"])
    assert {(n, m.name, horizon.setting_of(m)) for n, m in plan} == {
        (n, name, s) for n in horizon.ELEMENTS for name, s in
        (("lgvi", "dt=0.005"), ("lgvi", "dt=0.0025"), ("tsit5", "rtol=1e-06, atol=1e-08"), ("tsit5", "rtol=1e-08, atol=1e-10"))}
    assert horizon.finer(MethodSettings("x", {"dt": 0.01})).settings == {"dt": 0.005}


def test_a_rerun_merges_into_the_table_and_keeps_what_it_did_not_recompute(tmp_path):
    def history(name):
        return pd.DataFrame({"t": [0.0, 0.1, 0.2], "energy_error": [0.0, 1e-9, 2e-9], "tension_min": 1.0,
                             "method": f"{name} rtol=1e-06, atol=1e-08 N=10", "integrator": name, "scene": "fixed_length",
                             "elements": 10, "setting": "rtol=1e-06, atol=1e-08", "status": "ok", "t_end": 0.2,
                             "job_key": "from-an-earlier-run"})

    # tsit5's is a run of the study (kept); rk45 no longer declares energy-study settings: its
    # history is of a run the study does not make, and is dropped
    assert "rk45" not in {m.name for m in horizon.methods()}
    pd.concat([history("tsit5"), history("rk45")]).to_csv(tmp_path / "energy_horizon.csv", index=False)
    said = []
    one_size = (("elements", 4),)  # --set elements=4: that size only (one compilation per setting)
    figures = pipelines.run_horizon_study(0.2, tmp_path, one_size, jobs=0, log=said.append, selected=["lgvi"],
                                          scenes=["fixed_length"])
    table = pd.read_csv(tmp_path / "energy_horizon.csv")
    assert figures == [("energy_horizon_fixed_length.png", "")] and (tmp_path / figures[0][0]).is_file()
    runs = table.groupby(list(horizon.RUN_KEY)).size()
    assert len(runs) == 3 and runs[("fixed_length", 10, "tsit5", "rtol=1e-06, atol=1e-08")] == 3  # kept as it was
    assert "rk45" not in set(table["integrator"])
    assert set(table.loc[table.integrator == "lgvi", "setting"]) == {"dt=0.005", "dt=0.0025"}
    assert "tension_min" in table and table.loc[table.integrator == "lgvi", "tension_min"].notna().all()
    said.clear()
    pipelines.run_horizon_study(0.2, tmp_path, one_size, jobs=0, log=said.append, selected=["lgvi"],
                                scenes=["fixed_length"])
    assert any("kept 2 of 2 runs" in line for line in said)
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "energy_horizon.csv"), table)


def test_bad_input_is_refused_before_any_work(tmp_path, capsys):
    from benchmark.cli import main

    assert main(["energy", "--integrators", "no_such_method", "--out", str(tmp_path / "e")]) == 2
    assert capsys.readouterr().err.startswith("error:") and not (tmp_path / "e").exists()
    assert main(["energy", "--horizon", "0", "--out", str(tmp_path / "e")]) == 2


def test_run_makes_the_energy_study_only_when_given_a_horizon(tmp_path, monkeypatch, capsys):
    """The study is its own command (`energy`); `run` makes it too only with --horizon T, and
    only then checks its size (a horizon far too long is refused before any work)."""
    from benchmark.cli import main

    seen = []
    monkeypatch.setattr(pipelines, "run_sweep", lambda request, log: seen.append(request) or 0)
    run = ["run", "--quick", "--scenes", "fixed_length", "--integrators", "lgvi", "--out", str(tmp_path / "o")]
    assert main(run) == 0 and main([*run, "--horizon", "5"]) == 0 and main([*run, "--horizon", "0"]) == 0
    assert [r.energy_horizon for r in seen] == [0.0, 5.0, 0.0]
    assert main([*run, "--horizon", "1e9"]) == 2 and "--horizon 1e+09" in capsys.readouterr().err
    assert len(seen) == 3


def test_merge_study_table_replaces_a_run_as_a_whole_and_keeps_the_others():
    from benchmark.store import merge_study_table

    old = pd.DataFrame({"run": ["a", "a", "b"], "v": [1, 2, 3]})
    new = pd.DataFrame({"run": ["a"], "v": [9]})
    assert merge_study_table(old, new, ["run"]).to_dict("list") == {"run": ["b", "a"], "v": [3, 9]}
    assert merge_study_table(None, new, ["run"]).equals(new) and merge_study_table(old, None, ["run"]).equals(old)
