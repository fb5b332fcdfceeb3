"""A sweep you can stop, resume and trust, tested on real subprocesses.

The sweeps are tiny (fixed_length with one element, 0.04 s). A test-only plugin, `test_slow`
(the LGVI, sleeping before steps smaller than 6 ms while REELBENCH_TEST_SLEEP is set), keeps
a worker busy for as long as a test needs, so a signal always lands mid-sweep.
"""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
from _helpers import installed_plugin

ROOT = Path(__file__).resolve().parent.parent

PLUGIN = '''
import os
import time

from reelbench.integrators.lgvi import LGVI


class SlowLGVI(LGVI):
    """The LGVI, asleep for REELBENCH_TEST_SLEEP seconds before a run with dt < 6 ms."""

    name = "test_slow"
    description = "test only: the LGVI, slow on purpose"

    def solve(self, scene, t_end=None, *, dt=None, **kw):
        if dt is not None and dt < 0.006:
            time.sleep(float(os.environ.get("REELBENCH_TEST_SLEEP", "0")))
        return super().solve(scene, t_end, dt=dt, **kw)
'''


@pytest.fixture
def plugin_env(tmp_path):
    """Environment in which `python -m benchmark` (and its spawned workers) find `test_slow`."""
    site = installed_plugin(tmp_path / "site", "reelbench_slow_plugin", PLUGIN,
                            "test_slow = reelbench_slow_plugin:SlowLGVI")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(site)]), REELBENCH_TEST_SLEEP="60")
    return env


def _sweep(out: Path, env: dict, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "benchmark", "run", "--scenes", "fixed_length", "--integrators", "test_slow",
           "--dts", "0.01,0.005", "--t-end", "0.04", "--set", "elements=1", "--no-figures", "--repeats", "1",
           "--jobs", "1", "--out", str(out), *extra]
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid``."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[1]) == pid and fields[0] != "Z":
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _wait_for(cond, timeout: float, what: str, proc=None) -> None:
    t0 = time.monotonic()
    while not cond():
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"the sweep ended (rc {proc.returncode}) before {what}: {proc.stderr.read()}")
        if time.monotonic() - t0 > timeout:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.2)


def _rows(path: Path) -> int:
    try:
        return len(pd.read_csv(path))
    except (OSError, pd.errors.EmptyDataError):
        return 0


pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the workers")


@pytest.mark.parametrize("sig, rc, name", [(signal.SIGINT, 130, "Ctrl-C"), (signal.SIGTERM, 143, "SIGTERM")])
def test_a_signal_stops_the_sweep_at_once_saves_the_rows_and_leaves_no_worker(tmp_path, plugin_env, sig, rc, name):
    out = tmp_path / "out"
    proc = _sweep(out, plugin_env)
    if sig == signal.SIGINT:
        # the fast run (dt = 0.01) is saved; the slow one (dt = 0.005) keeps the worker busy for 60 s
        _wait_for(lambda: _rows(out / "runs.csv") >= 1, 240, "the first row", proc)
    else:  # as soon as the pool has started: nothing finished yet
        _wait_for(lambda: _children(proc.pid), 60, "the worker", proc)
        time.sleep(1.0)
    workers = _children(proc.pid)
    assert workers, "the sweep has no worker processes"
    t0 = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=30)
    took = time.monotonic() - t0
    assert proc.returncode == rc, err
    assert took < 8, f"took {took:.1f} s to stop"
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    saved = "1 finished run(s) are saved in" if sig == signal.SIGINT else "no run had finished, nothing saved"
    assert last.startswith(f"stopped by {name}: {saved}") and "resume" in last, last
    _wait_for(lambda: not any(_alive(w) for w in workers), 5, "the workers to exit")
    assert _rows(out / "runs.csv") == (1 if sig == signal.SIGINT else 0)
    assert not (out / ".reelbench.lock").exists()


def test_killed_sweep_leaves_no_worker_and_a_rerun_resumes(tmp_path, plugin_env):
    out = tmp_path / "out"
    proc = _sweep(out, plugin_env)
    _wait_for(lambda: _rows(out / "runs.csv") >= 1, 240, "the first row", proc)
    workers = _children(proc.pid)
    assert workers
    kept = pd.read_csv(out / "runs.csv")
    proc.kill()  # kill -9: no handler runs; the workers must notice by themselves
    proc.communicate(timeout=10)
    _wait_for(lambda: not any(_alive(w) for w in workers), 10, "the orphaned workers to exit")
    assert (out / ".reelbench.lock").exists()  # left behind by the killed run, its kernel lock gone with it ...

    env = dict(plugin_env, REELBENCH_TEST_SLEEP="0")
    again = _sweep(out, env)
    _, err = again.communicate(timeout=240)
    assert again.returncode == 0, err  # ... so it blocks nobody
    assert not (out / ".reelbench.lock").exists()
    assert "resuming: 1 of 2 runs already done" in err, err
    assert err.count("] fixed_length test_slow") == 1, err  # only the missing run was computed
    rows = pd.read_csv(out / "runs.csv")
    assert list(rows["setting"]) == ["dt=0.01", "dt=0.005"] and (rows["status"] == "ok").all()
    # the kept row is the earlier one, unchanged (its timing would differ if recomputed)
    assert rows.iloc[0]["run_time"] == kept.iloc[0]["run_time"]
    assert rows.iloc[0]["run_key"] == kept.iloc[0]["run_key"]


def test_fresh_ignores_the_rows_already_there(tmp_path, monkeypatch):
    from reelbench.benchmark.cli import main as cli
    from reelbench.benchmark.core import study
    from reelbench.benchmark.runs import table

    class Stop(Exception):
        pass

    seen = {}

    def kept(the_study, earlier):  # the earlier rows the runner may keep instead of computing
        seen["previous"] = [r for r in earlier if the_study.reusable(r)]
        raise Stop

    earlier = {"run_key": "x", "status": "ok", "scene": "elsewhere", "integrator": "lgvi", "setting": "dt=0.01"}
    monkeypatch.setattr(table, "read_runs", lambda *a, **k: table.StoredRuns([earlier], []))
    monkeypatch.setattr(study, "_kept", kept)
    args = ["run", "--scenes", "fixed_length", "--integrators", "lgvi", "--dts", "0.01", "--t-end", "0.02",
            "--no-figures", "--out", str(tmp_path)]
    for extra, previous in (([], [earlier]), (["--fresh"], [])):
        with pytest.raises(Stop):
            cli.main(args + extra)
        assert seen["previous"] == previous


# ------------------------------------------------------------------------------------------
# the lock

def test_a_second_run_into_a_locked_out_is_refused_naming_the_lock_and_holder(tmp_path, capsys):
    from reelbench.benchmark.cli.main import main
    from reelbench.benchmark.core.store import OutputLock

    with OutputLock(tmp_path) as lock:
        rc = main(["run", "--scenes", "fixed_length", "--integrators", "lgvi", "--dts", "0.01", "--t-end", "0.02",
                   "--no-figures", "--out", str(tmp_path)])
        assert lock.path.exists()
    err = capsys.readouterr().err
    assert rc == 2, err
    assert str(lock.path) in err and f"pid {os.getpid()}" in err and err.startswith("error:"), err
    assert not lock.path.exists()  # released


def test_the_lock_file_of_a_dead_process_blocks_nobody(tmp_path):
    from reelbench.benchmark.core.store import OutputLock

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    import socket

    (tmp_path / OutputLock.NAME).write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(),
                                                        "command": "an earlier run with a longer command line"}))
    with OutputLock(tmp_path) as lock:
        assert json.loads(lock.path.read_text())["pid"] == os.getpid()  # the holder, rewritten whole


def test_a_second_process_is_refused_at_once_naming_the_directory_and_holder(tmp_path):
    """The lock is the kernel's: another process is refused while this one holds it, and takes
    it as soon as this one is gone, even killed with -9."""
    from reelbench.benchmark.core.store import OutputLock

    probe = ("import sys, time\nfrom benchmark.core.store import OutputLock, LockedError\nt = time.perf_counter()\n"
             "try:\n    OutputLock(sys.argv[1]).acquire()\nexcept LockedError as e:\n"
             "    print(f'{time.perf_counter() - t:.3f}', e)\nelse:\n    print('taken')\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def other() -> str:
        return subprocess.run([sys.executable, "-c", probe, str(tmp_path)], capture_output=True, text=True,
                              env=env, cwd=ROOT, timeout=120).stdout.strip()

    with OutputLock(tmp_path):
        said = other()
        took, message = said.split(" ", 1)
        assert float(took) < 1.0, said
        assert f"{tmp_path}/ is in use by another run (pid {os.getpid()} on " in message, said
    assert other() == "taken"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom benchmark.core.store import OutputLock\n"
                               "held = OutputLock(sys.argv[1]).acquire()\nprint('held', flush=True)\ntime.sleep(600)",
                               str(tmp_path)], stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        assert holder.stdout.readline() == "held\n"
        assert f"(pid {holder.pid} on " in other()
    finally:
        holder.kill()
        holder.wait()
    assert other() == "taken"


def test_resume_keeps_only_rows_of_the_same_sweep():
    """The run key changes with the scene's physics, the setting, the horizon and the code."""
    from reelbench.benchmark.runs.table import run_key
    from reelbench.benchmark.runs.sweep import Task

    base = Task("fixed_length", "lgvi", dt=0.01, t_end=0.1, overrides=(("elements", 2),))
    key = run_key(base, "code1")
    assert run_key(base, "code1") == key
    assert run_key(Task("fixed_length", "lgvi", dt=0.01, t_end=0.1, overrides=(("elements", 3),)), "code1") != key
    assert run_key(Task("fixed_length", "lgvi", dt=0.005, t_end=0.1, overrides=(("elements", 2),)), "code1") != key
    assert run_key(Task("fixed_length", "lgvi", dt=0.01, t_end=0.2, overrides=(("elements", 2),)), "code1") != key
    assert run_key(Task("fixed_length", "rk45", dt=0.01, t_end=0.1, overrides=(("elements", 2),)), "code1") != key
    assert run_key(base, "code2") != key
    # the same physics under another name is the same run
    path = ROOT / "models" / "scenes" / "fixed_length.toml"
    assert run_key(Task(str(path), "lgvi", dt=0.01, t_end=0.1, overrides=(("elements", 2),)), "code1") == key


def test_worker_pool_workers_exit_when_their_parent_dies(tmp_path):
    """Without the sweep around it: a pool created in a child process that is then killed."""
    script = textwrap.dedent(f"""
        import os, sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from reelbench.benchmark.core.engine import worker_pool
        pool = worker_pool(2)
        futs = [pool.submit(time.sleep, 60) for _ in range(2)]
        time.sleep(0.5)
        print(" ".join(str(p) for p in pool._processes), flush=True)
        time.sleep(600)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    workers = [int(p) for p in proc.stdout.readline().split()]
    assert len(workers) == 2 and all(_alive(w) for w in workers)
    proc.kill()
    proc.wait()
    _wait_for(lambda: not any(_alive(w) for w in workers), 10, "the orphaned workers to exit")


def test_dask_workers_get_one_xla_thread_and_run_the_sweep(tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    from reelbench.benchmark.cli.main import main

    monkeypatch.delenv("XLA_FLAGS", raising=False)  # the workers must get it from the runner, not inherit it
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        rc = main(["run", "--executor", "dask", "--scheduler", cluster.scheduler_address, "--scenes", "fixed_length",
                   "--integrators", "lgvi", "--dts", "0.01", "--t-end", "0.04", "--set", "elements=1",
                   "--no-figures", "--repeats", "1", "--out", str(tmp_path)])
        assert rc == 0
        with distributed.Client(cluster.scheduler_address) as client:
            flags = list(client.run(lambda: os.environ.get("XLA_FLAGS")).values())
    from reelbench.models._jax import DEFAULT_XLA_FLAGS  # reelbench's own options, then the worker's one thread

    one_thread = ["--xla_cpu_multi_thread_eigen=false", "intra_op_parallelism_threads=1"]
    assert flags == [" ".join([*DEFAULT_XLA_FLAGS, *one_thread])]
    assert (pd.read_csv(tmp_path / "runs.csv")["status"] == "ok").all()
