"""The experiment engine (`benchmark.core.engine.run_jobs`) that every study runs on: rows in job
order, one worker per group, longest groups first, crash rows, progress."""

import os

import numpy as np
import pytest

from reelbench.benchmark.core import engine
from reelbench.benchmark.runs import runner
from reelbench.benchmark.studies import stability
from reelbench.benchmark.core import store


def job(spec: tuple) -> dict:
    """A job for the spawned workers, (name,) or (name, crash): its row says which process ran it."""
    name, crash = spec[0], spec[1:] == (True,)
    if crash:
        os._exit(7)  # the worker dies
    return {"name": name, "pid": os.getpid()}


def crashed(i, exc):
    return {"name": f"crash{i}", "status": "crashed", "reason": engine.crash_reason(exc)}


def test_in_process_longest_group_first_rows_in_job_order_progress_and_partial_writes():
    jobs = [("a1",), ("b1",), ("a2",), ("c1",)]
    ran, logged, saved = [], [], []

    def fn(spec):
        ran.append(spec[0])
        return {"name": spec[0]}

    rows = engine.run_jobs(fn, jobs, workers=0, crash_row=crashed, group=lambda i: jobs[i][0][0],
                           cost=lambda i: {"a": 1.0, "b": 5.0, "c": 2.0}[jobs[i][0][0]],
                           done={3: {"name": "c1 (kept)"}}, describe=lambda r: r["name"], log=logged.append,
                           on_row=lambda rs: saved.append([r["name"] for r in rs]))
    assert ran == ["b1", "a1", "a2"]  # group b (cost 5) before a (1 + 1); the kept job is not run
    assert [r["name"] for r in rows] == ["a1", "b1", "a2", "c1 (kept)"]
    assert saved[0] == ["c1 (kept)"] and saved[-1] == [r["name"] for r in rows]
    assert logged[0].startswith("[2/4] b1") and "s left" in logged[0] and "s left" not in logged[-1]


def test_workers_one_process_per_group_and_a_crash_is_a_row_then_a_fresh_worker():
    jobs = [("a1",), ("a2",), ("boom", True), ("b1",)]
    rows = engine.run_jobs(job, jobs, workers=1, crash_row=crashed,
                           group=lambda i: "b" if jobs[i][0] == "b1" else "a", log=lambda s: None)
    assert [r["name"] for r in rows] == ["a1", "a2", "crash2", "b1"]
    assert rows[0]["pid"] == rows[1]["pid"] != os.getpid()  # one worker ran the group
    assert rows[2]["status"] == "crashed" and "BrokenProcessPool" in rows[2]["reason"]
    assert rows[3]["pid"] != rows[0]["pid"]  # the dead worker was replaced


def test_stability_runs_on_the_engine_grouped_by_scene_and_method(monkeypatch):
    jobs = stability.jobs_for(scenes=["near_slack", "fast_spin"], integrators=["tsit5", "lgvi"])
    calls = []

    def fake_run_job(job):
        calls.append((job.case.scene, job.integrator, job.kind))
        if job.integrator == "lgvi" and job.case.scene == "fast_spin":
            raise AssertionError("unreachable")  # replaced by a crash row below
        return {**stability._base_row(job.case, job.integrator, job.kind), "status": "ok", "bounded": True,
                "steps": 10.0, "job_time": 0.0, "largest_stable_dt": 0.01 if job.kind == "fixed" else np.nan}

    def fake_run_jobs(fn, jobs_, **kw):
        assert kw["group"](0) == (jobs_[0].case.scene, jobs_[0].integrator)
        kw.pop("workers")
        rows = []
        for i, j in enumerate(jobs_):
            try:
                rows.append(fn(j))
            except AssertionError as exc:
                rows.append(kw["crash_row"](i, exc))
        return rows

    monkeypatch.setattr(stability, "run_job", fake_run_job)
    real = engine.run_jobs
    monkeypatch.setattr(engine, "run_jobs", fake_run_jobs)
    df = stability.execute(jobs, workers=2, log=lambda s: None)
    assert list(df.columns) == stability.COLUMNS and len(df) == len(jobs)
    crash = df[df["status"] == "crashed"]
    assert len(crash) == 1 and not crash.iloc[0]["bounded"] and crash.iloc[0]["integrator"] == "lgvi"
    monkeypatch.setattr(engine, "run_jobs", real)
    calls.clear()
    logged = []
    ok_jobs = [j for j in jobs if not (j.integrator == "lgvi" and j.case.scene == "fast_spin")]
    df = stability.execute(ok_jobs, workers=0, log=logged.append)
    # tsit5's ladder and adaptive run on a scene are one group: they run one after the other
    for scene in ("near_slack", "fast_spin"):
        k = calls.index((scene, "tsit5", "fixed"))
        assert calls[k + 1] == (scene, "tsit5", "adaptive")
    assert len(logged) == len(ok_jobs) and "largest stable dt 0.01 s" in " ".join(logged)


def test_frame_one_helper_for_both_tables():
    df = runner.runs_frame([{"scene": "s", "status": "diverged", "position_error_final": 1.0, "extra": 1}])
    assert np.isnan(df["position_error_final"].iloc[0]) and "extra" in df  # runs table: unfinished -> NaN
    df = store.frame([{"b": 1, "z": 2}], ["a", "b"], extra=False)
    assert list(df.columns) == ["a", "b"] and np.isnan(df["a"].iloc[0])
    assert list(store.frame([], ["a"]).columns) == ["a"]


def test_a_horizon_run_whose_worker_died_is_a_row_without_history():
    from reelbench.benchmark.studies import horizon
    from reelbench.benchmark.runs.sweep import MethodSettings

    job = horizon.Job("fixed_length", 10, MethodSettings("lgvi", {"dt": 0.005}), 1.0, ())
    dead = horizon.crash_row(job, RuntimeError("worker died"))
    assert dead["label"] == "lgvi dt=0.005 N=10 [crashed]" and dead["history"] is None and "worker died" in dead["reason"]


if __name__ == "__main__":
    pytest.main([__file__])


def test_progress_in_a_log_or_a_file_is_lines_only(capsys):
    """Not a terminal (a CI log, a file): one line per job, no bar, no carriage returns."""
    rows = engine.run_jobs(lambda x: {"x": x}, list(range(5)), workers=0, cost=lambda i: 1.0 + i,
                           describe=lambda r: f"job {r['x']}")
    err = capsys.readouterr().err
    assert len(rows) == 5 and "\r" not in err and "%|" not in err, err
    assert err.splitlines()[0].startswith("[1/5] job 4  (") and len(err.splitlines()) == 5, err


def test_on_a_terminal_a_bar_is_drawn_below_the_lines_and_taken_away():
    import fcntl
    import pty
    import struct
    import subprocess
    import sys
    import termios

    script = ("from reelbench.benchmark.core import engine\nimport time\n"
              "engine.run_jobs(lambda x: time.sleep(0.05) or {'x': x}, list(range(3)), workers=0,"
              " cost=lambda i: 1.0, describe=lambda r: f\"job {r['x']}\")\n"
              "engine.log_stderr('after')\n")
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))  # a terminal 80 wide
    proc = subprocess.Popen([sys.executable, "-c", script], stderr=follower, cwd=os.path.dirname(os.path.dirname(__file__)))
    os.close(follower)
    out = b""
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # the child is gone
            break
        if not chunk:
            break
        out += chunk
    assert proc.wait(timeout=60) == 0
    text = out.decode()
    assert "3 jobs" in text and "%|" in text and "\r" in text, text  # the bar, redrawn in place
    assert [line for line in ("job 0", "job 1", "job 2", "after") if line in text] == ["job 0", "job 1", "job 2", "after"]
    assert text.rstrip().endswith("after"), repr(text[-200:])  # the bar was taken away before the last line
