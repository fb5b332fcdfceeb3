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
    out = tmp_path / "t.npz"
    rc = main(["simulate", "fixed_length", "--set", "elements=1", "--dt", "0.001", "--t-end", "20000",
               "--time-limit", "1", "--save-every", "0.1", "--out", str(out)])
    err = _err(capsys)
    assert rc == 1 and "status time_limit stopped by time_limit = 1 s" in err, err
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
