"""Unbounded work is never done on request: `simulate` runs within a default step and wall-clock
budget (raised by --max-steps / --time-limit), a stopped `simulate` saves what it has, and an
archive is size-checked before any of it is read. A trajectory carries its scene, so `figures`
draws one computed from a scene file without that file."""

import os
import signal
import zipfile

import numpy as np
import pytest

from reelbench.benchmark.core import options as opt
from reelbench.benchmark.cli.main import main


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err


def test_simulate_runs_within_default_budgets_that_options_raise(monkeypatch, tmp_path, capsys):
    """The issue's request (rk45 at rtol 1e-13 to t = 1e5 s) gets the default budgets; the options
    raise them."""
    from reelbench.benchmark.cli import simulate

    seen = []
    monkeypatch.setattr(simulate, "simulate", lambda scene, integ, settings, out, **k: seen.append(settings) or 0)
    out = str(tmp_path / "t.npz")
    assert main(["simulate", "fixed_length", "--integrators", "rk45", "--rtol", "1e-13", "--t-end", "1e5",
                 "--out", out]) == 0
    assert seen[-1]["max_steps"] == opt.SOLVE_MAX_STEPS and seen[-1]["time_limit"] == opt.SOLVE_TIME_LIMIT
    assert main(["simulate", "fixed_length", "--integrators", "rk45", "--rtol", "1e-13", "--t-end", "1e5",
                 "--max-steps", "20000000", "--time-limit", "7200", "--out", out]) == 0
    assert seen[-1]["max_steps"] == 20_000_000 and seen[-1]["time_limit"] == 7200.0
    for bad in (["--max-steps", "0"], ["--time-limit", "-1"], ["--time-limit", "nan"]):
        assert main(["simulate", "fixed_length", "--dt", "0.01", "--out", out, *bad]) == 2
        assert "error: argument " + bad[0] in _err(capsys)


def test_a_run_out_of_its_time_budget_ends_with_its_trajectory_saved(tmp_path, capsys):
    """3 s: on a loaded machine the first chunk of steps alone can take over 1 s."""
    out = tmp_path / "t.npz"
    rc = main(["simulate", "fixed_length", "--set", "elements=1", "--dt", "0.001", "--t-end", "20000",
               "--time-limit", "3", "--save-every", "0.1", "--out", str(out)])
    err = _err(capsys)
    assert rc == 1 and "status time_limit stopped by time_limit = 3 s" in err, err
    from reelbench.benchmark.core.store import read_trajectory

    traj = read_trajectory(out)
    assert traj.status == "time_limit" and 0 < traj.t[-1] < 20000 and out.with_suffix(".csv").is_file()


def test_a_first_ctrl_c_ends_simulate_where_it_is_and_saves_it(tmp_path, monkeypatch, capsys):
    """The first clock check of the run sends this process SIGINT: the run ends at the next check,
    its trajectory is saved, one line says where, exit 130."""
    from reelbench.integrators import lifecycle

    real = lifecycle.Run.out_of_time
    sent = []

    def out_of_time(self):
        if not sent:
            sent.append(os.kill(os.getpid(), signal.SIGINT))
        return real(self)

    monkeypatch.setattr(lifecycle.Run, "out_of_time", out_of_time)
    out = tmp_path / "t.npz"
    rc = main(["simulate", "fixed_length", "--set", "elements=1", "--dt", "0.001", "--t-end", "20000",
               "--save-every", "10", "--out", str(out)])
    err = _err(capsys)
    assert rc == 130, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("stopped by Ctrl-C: the run up to t = ") and f"is saved in {out}" in last, err
    from reelbench.benchmark.core.store import read_trajectory

    traj = read_trajectory(out)
    assert traj.t[-1] < 20000 and traj.reason.startswith("stopped by Ctrl-C at t = ")
    assert not lifecycle.STOP_REQUESTED.is_set()  # the next solve is not stopped


def test_an_archive_that_expands_past_the_limit_is_refused_before_it_is_read(tmp_path, monkeypatch, capsys):
    from reelbench.benchmark.core import store

    monkeypatch.setattr(store, "MAX_ARCHIVE_BYTES", 2**20)
    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("t.npy", b"\0" * (4 * 2**20))  # 4 MiB of zeros: a few KiB on disk
    assert bomb.stat().st_size < 2**16
    monkeypatch.setattr(np, "load", lambda *a, **k: pytest.fail("read the archive"))
    assert main(["figures", str(bomb), "--out", str(tmp_path / "f.png")]) == 2
    err = _err(capsys)
    assert "its arrays expand to 0.00391 GiB, over the 0.000977 GiB that are read back" in err, err
    with pytest.raises(store.UnreadableFile, match="expand to"):
        store.read_npz(bomb)


def test_figures_of_a_trajectory_from_a_scene_file_needs_no_scene_option(tmp_path, capsys):
    from reelbench.models.scene import SCENE_DIR

    scene = tmp_path / "damped_tip.toml"
    scene.write_text((SCENE_DIR / "fixed_length.toml").read_text().replace('name = "fixed_length"',
                                                                             'name = "damped_tip"'))
    traj = tmp_path / "t.npz"
    assert main(["simulate", str(scene), "--set", "elements=2", "--dt", "0.01", "--t-end", "0.2",
                 "--out", str(traj)]) == 0
    os.remove(scene)  # the trajectory carries the scene
    assert main(["figures", str(traj), "--out", str(tmp_path / "f.png")]) == 0, _err(capsys)
    assert (tmp_path / "f.png").stat().st_size > 10_000


def test_every_solve_of_a_sweep_has_a_budget_and_a_run_past_it_is_a_status_not_a_hang(tmp_path):
    """`run`, `stability` and `check` bound each first solve (`runner.SolveBudget`): a run past
    its steps or seconds is a row with status max_steps / time_limit; the timed repeats are the
    same unbudgeted work (no chunked loop is timed)."""
    from reelbench.benchmark.runs import runner
    from reelbench.benchmark.runs.sweep import Task

    long = Task("fixed_length", "lgvi", dt=0.001, t_end=5000.0, save_every=1.0, overrides=(("elements", 1),))
    row = runner.run_task(long, cache_dir=str(tmp_path), repeats=0, reference=False,
                          budget=runner.SolveBudget(time_limit=0.5))
    assert row["status"] == "time_limit" and "stopped by time_limit = 0.5 s" in row["reason"], row
    row = runner.run_task(long, cache_dir=str(tmp_path), repeats=0, reference=False,
                          budget=runner.SolveBudget(max_steps=100))
    assert row["status"] == "max_steps", row
    short = Task("fixed_length", "lgvi", dt=0.01, t_end=0.2, overrides=(("elements", 2),))
    row = runner.run_task(short, cache_dir=str(tmp_path), repeats=2, reference=False)
    assert row["status"] == "ok" and row["timing_repeats"] >= 2, row
    assert runner.SolveBudget() == runner.SolveBudget(opt.SOLVE_MAX_STEPS, opt.SOLVE_TIME_LIMIT)


def test_the_studies_take_their_budget_from_the_command_line(monkeypatch, tmp_path):
    from reelbench.benchmark.core import study
    from reelbench.benchmark.studies import check, grid
    from reelbench.benchmark.runs.runner import SolveBudget

    seen = {}
    monkeypatch.setattr(grid, "run_sweep", lambda request, log=None: seen.update(run=request.budget) or 0)
    monkeypatch.setattr(study, "run", lambda s, *a, **k: seen.update(stability=s.jobs[0].budget) or 0)
    monkeypatch.setattr(check, "run_check", lambda *, budget=None, **k: seen.update(check=budget) or 0)
    assert main(["run", "--quick", "--scenes", "fixed_length", "--integrators", "lgvi", "--out", str(tmp_path / "r"),
                 "--time-limit", "30", "--max-steps", "1000"]) == 0
    assert main(["stability", "--scenes", "stiff_string", "--integrators", "lgvi", "--out", str(tmp_path / "s")]) == 0
    assert main(["check", "--integrators", "lgvi", "--time-limit", "7200"]) == 0
    assert seen == {"run": SolveBudget(1000, 30.0), "stability": SolveBudget(),
                    "check": SolveBudget(opt.SOLVE_MAX_STEPS, 7200.0)}


# ------------------------------------------------------------------------------------------
# The budgets of orders, energy, speed and reel-reversal
# ------------------------------------------------------------------------------------------
#: Each study command with a small out of its own (the budget options are the same builder's).
STUDIES = {"orders": ["--scenes", "fixed_length", "--integrators", "lgvi"],
           "energy": ["--integrators", "lgvi", "--variants", "plain"],
           "speed": ["--integrators", "lgvi", "--rhs", ""],
           "reel-reversal": ["--integrators", "lgvi"]}


def _out(command: str, tmp_path) -> list[str]:
    return ["--out", str(tmp_path / ("o.md" if command == "speed" else "o"))]


@pytest.mark.parametrize("command", STUDIES)
@pytest.mark.parametrize("bad, allowed", [(["--max-steps", "0"], "is invalid (allowed: an integer >= 1)"),
                                          (["--time-limit", "0"], "is invalid (allowed: a finite number > 0)"),
                                          (["--time-limit", "nan"], "is not a finite number")])
def test_a_study_refuses_a_budget_out_of_range_before_any_work(command, bad, allowed, tmp_path, capsys):
    assert main([command, *STUDIES[command], *_out(command, tmp_path), *bad]) == 2
    err = _err(capsys)
    assert f"error: argument {bad[0]}: '{bad[1]}' {allowed}" in err, err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("command", STUDIES)
def test_a_study_s_jobs_carry_the_budget_of_its_options(command, monkeypatch, tmp_path):
    """Every job of the study gets the budget the options give (the defaults without them)."""
    from reelbench.benchmark.core import study
    from reelbench.benchmark.runs.runner import SolveBudget

    seen = []
    monkeypatch.setattr(study, "run", lambda s, *a, **k: seen.append({j.budget for j in s.jobs}) or 0)
    assert main([command, *STUDIES[command], *_out(command, tmp_path)]) == 0
    assert main([command, *STUDIES[command], *_out(command, tmp_path), "--max-steps", "7", "--time-limit", "3"]) == 0
    assert seen == [{SolveBudget()}, {SolveBudget(7, 3.0)}]


def test_the_default_budget_keeps_a_job_s_key_and_another_one_changes_it():
    """Rows made before the budgets were options keep their resume key; a row made under another
    budget is made again when the defaults are asked for."""
    from reelbench.benchmark.runs.runner import SolveBudget
    from reelbench.benchmark.studies import horizon, lgvi_speed, orders, reel_reversal
    from reelbench.benchmark.runs.sweep import MethodSettings

    jobs = {orders.key: orders.Job("fixed_length", "lgvi"),
            reel_reversal.key: reel_reversal.Job("lgvi", 0.004, "reel_reversal", 5, 0.96, "/tmp"),
            horizon.key: horizon.Job("fixed_length", 4, MethodSettings("lgvi", {"dt": 0.005}), 10.0, ()),
            lgvi_speed.key: lgvi_speed.StepJob("lgvi", "fixed_length", 10, 2000, 3, None)}
    for key, job in jobs.items():
        plain = key(job)
        assert key(job._replace(budget=SolveBudget())) == plain
        assert key(job._replace(budget=SolveBudget(max_steps=7))) != plain


def test_a_ladder_run_and_a_speed_measurement_past_their_budget_say_so():
    """The budget reaches the solves: every run of a ladder past 3 steps ends with status
    max_steps (the ladder goes on), and so does a speed measurement (not timed)."""
    from reelbench.benchmark.runs.runner import SolveBudget
    from reelbench.benchmark.studies import lgvi_speed, orders

    ref = orders.Reference("fixed_length", np.zeros((17, 3)), 1e-14, 1e-14)
    row = orders.run_job(orders.Job("fixed_length", "lgvi", ref, budget=SolveBudget(max_steps=3)))
    assert [r["status"] for r in row["ladder"]] == ["max_steps"] * (orders.HALVINGS + 1), row
    m = lgvi_speed.measure("fixed_length", 2, 50, 1, method="lgvi", budget=SolveBudget(max_steps=3))
    assert m["status"] == "max_steps" and np.isnan(m["us_per_step"]), m


def test_the_answer_s_searches_take_their_budget_from_the_command_line(monkeypatch, tmp_path, capsys):
    """`answer --max-steps/--time-limit` reach every search job (the defaults: no step cap and the
    search's own time limit), and out-of-range values are refused before any work."""
    from reelbench.benchmark.answer import answer
    from reelbench.benchmark.core.policy import SEARCH_TIME_LIMIT

    seen = []
    monkeypatch.setattr(answer, "run_answer", lambda request, log=None: seen.append(request) or 0)
    args = ["answer", "--scenes", "fixed_length", "--integrators", "lgvi", "--out", str(tmp_path / "o")]
    assert main(args) == 0 and main([*args, "--max-steps", "7", "--time-limit", "3"]) == 0
    budgets = [{(j.max_steps, j.time_limit) for j in answer.search_study(r, "/tmp", answer._Merged(answer.SEARCH_COLUMNS)).jobs}
               for r in seen]
    assert budgets == [{(None, SEARCH_TIME_LIMIT)}, {(7, 3.0)}]
    for bad, allowed in ((["--max-steps", "0"], "is invalid (allowed: an integer >= 1)"),
                         (["--time-limit", "nan"], "is not a finite number")):
        assert main([*args, *bad]) == 2
        assert f"error: argument {bad[0]}: '{bad[1]}' {allowed}" in _err(capsys)
