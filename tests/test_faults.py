"""Disk and file-system faults during work: each is one `error: ...` line naming the file, exit
status 1 (2 when it is found before any work), no traceback, no temporary file left behind,
and what had finished saved where the disk still takes it.

A full disk is simulated by making the atomic writer's rename (or one chosen target) fail with
ENOSPC, as a real full disk fails the write before it."""

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from reelbench.benchmark.cli.main import main
from reelbench.models import io as model_io

#: The smallest sweep: one scene, one method, two steps, no figures, in this process.
TINY = ["run", "--scenes", "fixed_length", "--integrators", "lgvi", "--t-end", "0.04", "--set", "elements=1",
        "--no-figures", "--executor", "serial", "--repeats", "1"]


def disk_full(monkeypatch, when=lambda target: True):
    """Every atomic write whose target passes ``when`` fails with ENOSPC (the others succeed)."""
    real = os.replace

    def replace(src, dst, *a, **k):
        if Path(dst).name.startswith(".") is False and when(Path(dst)):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(model_io.os, "replace", replace)


def leftovers(root: Path) -> list[str]:
    return sorted(p.name for p in root.rglob("*") if ".tmp" in p.name)


def outcome(capsys) -> tuple[str, str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err, err.strip().splitlines()[-1]


def test_atomic_writer_names_the_file_and_leaves_nothing_behind(tmp_path, monkeypatch):
    target = tmp_path / "table.csv"
    target.write_text("old\n")
    disk_full(monkeypatch)
    with pytest.raises(model_io.WriteFailed) as err:
        model_io.atomic_write_text(target, "new\n")
    assert str(err.value) == f"cannot write {target}: No space left on device"
    assert err.value.errno == errno.ENOSPC
    assert target.read_text() == "old\n" and leftovers(tmp_path) == []


def test_a_directory_where_a_result_file_goes_is_named_as_such(tmp_path):
    (tmp_path / "table.csv").mkdir()
    with pytest.raises(model_io.WriteFailed, match="table.csv: a directory is in its place"):
        model_io.atomic_write_text(tmp_path / "table.csv", "x\n")
    assert leftovers(tmp_path) == []


def test_simulate_on_a_full_disk_says_so_and_exits_1(tmp_path, monkeypatch, capsys):
    disk_full(monkeypatch)
    out = tmp_path / "t.npz"
    rc = main(["simulate", "fixed_length", "--set", "elements=1", "--t-end", "0.04", "--dt", "0.01", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 1 and line.startswith(f"error: cannot write {out}: No space left on device"), err
    assert "is not saved" in line and not out.exists() and leftovers(tmp_path) == []


def test_a_sweep_on_a_disk_that_fills_keeps_the_rows_it_saved(tmp_path, monkeypatch, capsys):
    """The first row reaches runs.csv; the disk is full for the second: exit 1, the saved row
    intact, the line says how many are saved; the reference that could not be cached is used."""
    writes = []

    def full_after_first_table(target):
        if target.name == "runs.csv":
            writes.append(target)
            return len(writes) > 1
        return target.suffix == ".npz"  # the reference cache too

    from reelbench.benchmark.core import reference

    disk_full(monkeypatch, full_after_first_table)
    # an empty cache of references (the user's may hold this one already): the run must write it
    monkeypatch.setattr(reference, "CACHE_DIR", tmp_path / "references")
    out = tmp_path / "out"
    rc = main(TINY + ["--dts", "0.01,0.005", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 1, err
    assert line.startswith(f"error: cannot write {out / 'runs.csv'}: No space left on device"), line
    assert "1 finished run(s) are saved" in line and "run the same command again to resume" in line
    assert "is used without being cached" in err
    import pandas as pd

    saved = pd.read_csv(out / "runs.csv")
    assert len(saved) == 1 and saved["status"].iloc[0] == "ok"
    assert leftovers(tmp_path) == [] and not (out / ".reelbench.lock").exists()


def test_a_directory_in_place_of_a_result_file_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    from reelbench.benchmark.studies import grid

    monkeypatch.setattr(grid, "run_sweep", lambda *a, **k: pytest.fail("started the sweep"))
    (tmp_path / "out" / "runs.csv").mkdir(parents=True)
    rc = main(TINY + ["--dts", "0.01", "--out", str(tmp_path / "out")])
    err, line = outcome(capsys)
    assert rc == 2 and "runs.csv there is a directory" in line and "give another --out" in line, err


@pytest.mark.parametrize("kind", ["fifo", "link to /dev/zero"])
def test_a_special_file_in_place_of_the_runs_table_is_refused_without_reading_it(tmp_path, monkeypatch, capsys, kind):
    from reelbench.benchmark.studies import grid

    monkeypatch.setattr(grid, "run_sweep", lambda *a, **k: pytest.fail("started the sweep"))
    out = tmp_path / "out"
    out.mkdir()
    if kind == "fifo":
        os.mkfifo(out / "runs.csv")
    else:
        (out / "runs.csv").symlink_to("/dev/zero")
    rc = main(TINY + ["--dts", "0.01", "--out", str(out)])  # reading either would block or never end
    err, line = outcome(capsys)
    assert rc == 2 and "runs.csv there is not a regular file" in line, err


def test_a_directory_in_place_of_a_cached_reference_costs_the_cache_only(tmp_path, capsys):
    from reelbench.benchmark.core.reference import get_reference, reference_path
    from reelbench.models import load_scene

    scene = load_scene("fixed_length", elements=1)
    reference_path(scene, 0.04, 0.02, tmp_path).mkdir()
    said = []
    traj = get_reference(scene, 0.04, 0.02, tmp_path, log=said.append)
    assert traj.ok and np.isfinite(traj.x).all()
    assert any("is not used" in s for s in said) and any("without being cached" in s for s in said), said


def test_a_reference_that_cannot_finish_names_the_scene_and_the_fix(tmp_path, monkeypatch):
    """The reference solver has a step budget (scipy's adapters: max_steps); when it runs out the
    error names the scene, not just the solver's status."""
    from reelbench.benchmark.core import reference
    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    real = get_integrator(reference.REFERENCE_METHOD["integrator"])

    class Budgeted:
        def solve(self, scene, **kw):
            return real.solve(scene, **kw, max_steps=3)

    monkeypatch.setattr(reference, "get_integrator", lambda name: Budgeted())
    with pytest.raises(reference.ReferenceFailed) as err:
        reference.get_reference(load_scene("fixed_length", elements=1), 0.1, 0.02, tmp_path, log=None)
    msg = str(err.value)
    assert "scene 'fixed_length'" in msg and "max_steps = 3 reached" in msg and "Check the scene's values" in msg
    assert not list(tmp_path.iterdir())  # nothing cached


def test_a_fifo_in_place_of_a_cached_reference_is_not_opened(tmp_path):
    from reelbench.benchmark.core.reference import get_reference, reference_path
    from reelbench.models import load_scene

    scene = load_scene("fixed_length", elements=1)
    os.mkfifo(reference_path(scene, 0.04, 0.02, tmp_path))
    said = []
    assert get_reference(scene, 0.04, 0.02, tmp_path, log=said.append).ok  # would block in open() before
    assert any("named pipe (FIFO)" in s and "is not used" in s for s in said), said


def test_figures_on_a_full_disk_exit_1_naming_the_figure(tmp_path, monkeypatch, capsys):
    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    traj = get_integrator("lgvi").solve(load_scene("fixed_length", elements=1), t_end=0.04, dt=0.01)
    traj.save(tmp_path / "t.npz")
    disk_full(monkeypatch)
    rc = main(["figures", str(tmp_path / "t.npz"), "--set", "elements=1", "--out", str(tmp_path / "f.png")])
    err, line = outcome(capsys)
    assert rc == 1 and line == f"error: cannot write {tmp_path / 'f.png'}: No space left on device", err
    assert leftovers(tmp_path) == []


def test_a_read_only_output_place_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    """(Simulated: the tests may run as root, for whom a chmod'ed directory stays writable.)"""
    import tempfile

    def read_only(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    for args in (["simulate", "fixed_length", "--dt", "0.01", "--out", str(tmp_path / "t.npz")],
                 ["run", "--quick", "--out", str(tmp_path / "o")], ["stability", "--out", str(tmp_path / "o")]):
        rc = main(args)
        err, line = outcome(capsys)
        assert rc == 2 and "not writable (Read-only file system)" in line and "give a directory" in line, (args, err)
    assert not (tmp_path / "o").exists()


def test_a_scene_that_is_a_link_to_dev_zero_is_refused_at_once(tmp_path, capsys):
    (tmp_path / "zero.toml").symlink_to("/dev/zero")
    rc = main(["simulate", str(tmp_path / "zero.toml"), "--dt", "0.01"])
    err, line = outcome(capsys)
    assert rc == 2 and "zero.toml" in line and "character device" in line, err


# ------------------------------------------------------------------------------------------
# A stop signal during work: one line, the exit status a shell reports, no traceback
# ------------------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parent.parent
LONG = {  # each runs for minutes if not stopped
    "simulate": ["simulate", "fixed_length", "--dt", "1e-4", "--t-end", "2000", "--out", "{d}/t.npz"],
    "check": ["check", "--integrators", "lgvi,rk45", "--jobs", "1"],
    "stability": ["stability", "--scenes", "stiff_string", "--integrators", "lgvi", "--jobs", "0", "--out", "{d}/s"],
    "xval": ["xval", "--elements", "5,10,20,40,80,160", "--out", "{d}/x"],
    "speed": ["speed", "--elements", "10", "--scenes", "fixed_length", "--integrators", "lgvi", "--steps", "2000000",
              "--repeats", "50", "--rhs", "", "--out", "{d}/speed.md"],
}
#: simulate ends its run where it is and saves it; the studies keep (merge) what finished (xval is
#: stopped after its first job: that job's rows are kept)
EXPECTED = {"simulate": "is saved in", "check": "the baseline was not changed",
            "stability": "no row had finished", "xval": "finished row(s) are merged", "speed": "no row had finished"}
#: The line each command writes once it is past its checks and imports, at work: the signal is
#: sent after it (a fixed sleep raced the imports on a loaded machine). A stop in the imports
#: themselves is tested on its own (`test_a_stop_during_an_import_lands_when_the_import_ends`).
AT_WORK = {"simulate": ": started; estimated", "check": "[1/", "stability": "stability map:",
           "xval": "[1/", "speed": "speed: "}


#: SIGTERM to simulate and check in the fast suite (~7 s each: they had no handler at all); the rest slow.
SIGNALS = [pytest.param(c, sig, rc, name, id=f"{c}-{name}",
                        marks=[] if sig == 15 and c in ("simulate", "check") else pytest.mark.slow)
           for c in LONG for sig, rc, name in ((15, 143, "SIGTERM"), (2, 130, "Ctrl-C"))]


@pytest.mark.parametrize("command, sig, rc, name", SIGNALS)
def test_a_stop_signal_during_work_ends_the_command_with_one_line(tmp_path, command, sig, rc, name):
    import queue
    import subprocess
    import sys
    import threading

    args = [a.format(d=tmp_path) for a in LONG[command]]
    proc = subprocess.Popen([sys.executable, "-m", "benchmark", *args], cwd=ROOT, stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, text=True, start_new_session=True)
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(x) for x in iter(proc.stderr.readline, "")] + [lines.put(None)],
                              daemon=True)
    reader.start()
    seen: list[str] = []
    try:
        while not seen or AT_WORK[command] not in seen[-1]:
            line = lines.get(timeout=180)
            assert line is not None, f"{command} ended before it was at work: {''.join(seen)}"
            seen.append(line)
    except queue.Empty:
        os.killpg(proc.pid, 9)
        pytest.fail(f"{command} wrote no {AT_WORK[command]!r} line within 180 s: {''.join(seen)}")
    proc.send_signal(sig)
    try:  # simulate ends at its first check after compiling (a signal waits for compilation to end)
        proc.wait(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, 9)
        pytest.fail(f"{command} did not stop within 120 s of {name}")
    reader.join(10)  # the pipe closes with the process: every line is in the queue
    while (line := lines.get_nowait() if not lines.empty() else None) is not None:
        seen.append(line)
    err = "".join(seen)
    assert "Traceback" not in err and "leaked" not in err, err  # the pools' semaphores released too
    last = err.strip().splitlines()[-1]
    assert proc.returncode == rc and last.startswith(f"stopped by {name}"), (proc.returncode, err)
    assert EXPECTED[command] in last, last


def _stop_script(tmp_path, body: str) -> str:
    """Run ``body`` after the stop handlers are installed, in a fresh interpreter; its output."""
    import subprocess
    import sys
    import textwrap

    script = "import os, signal, sys, time\nfrom benchmark.core.engine import install_stop_handlers\n" \
             "install_stop_handlers()\n" + textwrap.dedent(body)
    out = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
                         capture_output=True, text=True, timeout=60)
    return out.stdout + out.stderr


def test_a_stop_that_lands_in_a_gc_callback_is_sent_again(tmp_path):
    """Python drops an exception raised in a gc callback (JAX runs one at every collection):
    the stop must still end the work, not be printed as 'Exception ignored' and forgotten."""
    out = _stop_script(tmp_path, """
        import gc
        def callback(phase, info):
            if phase == "start" and not getattr(callback, "sent", False):
                callback.sent = True
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(10000):  # the handler runs here, inside the callback
                    pass
        gc.callbacks.append(callback)
        gc.collect()
        try:
            time.sleep(5)
            print("not stopped")
        except KeyboardInterrupt as exc:
            print("stopped:", exc)
    """)
    assert "stopped: signal SIGTERM" in out and "not stopped" not in out and "Exception ignored" not in out, out


def test_a_stop_during_an_import_lands_when_the_import_ends(tmp_path):
    """An import interrupted half-way leaves a module half-initialised (JAX's C++ extensions
    aborted the interpreter at exit): the stop waits for the import, then stops the work."""
    (tmp_path / "slow_module.py").write_text(
        "import os, signal\nos.kill(os.getpid(), signal.SIGTERM)\nfor _ in range(200000):\n    pass\nDONE = True\n")
    out = _stop_script(tmp_path, """
        sys.path.insert(0, os.getcwd())
        try:
            import slow_module
            print("imported:", slow_module.DONE)
            time.sleep(5)
            print("not stopped")
        except KeyboardInterrupt as exc:
            print("stopped:", exc, "slow_module" in sys.modules)
    """)
    assert "imported: True" in out and "stopped: signal SIGTERM True" in out and "not stopped" not in out, out


@pytest.mark.parametrize("content, fragment", [
    ("[" + ".".join(["a"] * 2000) + "]\nx = 1\n", "nested"),
    ("# padding\n" * 200_000, "more than the 1,000,000"),
    ("\udcff", "not a text file"),
], ids=["2000 nested tables", "over the size limit", "binary"])
def test_a_scene_file_that_cannot_be_a_scene_is_one_error_line_for_every_command(tmp_path, capsys, content, fragment):
    path = tmp_path / "bad.toml"
    path.write_bytes(content.encode("utf-8", "surrogateescape"))
    for args in (["simulate", str(path), "--dt", "0.01"], ["run", "--scenes", str(path), "--out", str(tmp_path / "o")],
                 ["speed", "--scenes", str(path)], ["xval", "--scenes", str(path), "--out", str(tmp_path / "o")],
                 ["reel-reversal", "--scenes", str(path), "--cache-dir", str(tmp_path / "o")]):
        rc = main(args)
        err, line = outcome(capsys)
        assert rc == 2 and str(path) in line and fragment in line, (args, err)
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------------
# The results store fails closed: a table it cannot read whole is kept, its rows salvaged one
# by one; a row whose digest was removed or whose timings were edited is not trusted
# ------------------------------------------------------------------------------------------
def stored_row(scene="deployment", setting="dt=0.01", **values) -> dict:
    """A finished row as the runner writes it (with its digest), of a scene other than TINY's."""
    from reelbench.benchmark.runs import runner

    row = {"scene": scene, "scene_key": "abc", "integrator": "lgvi", "setting": setting, "dt": 0.01,
           "rtol": np.nan, "atol": np.nan, "t_end": 2.0, "status": "ok", "reason": "", "rhs": "closed_form",
           "steps": 200, "newton_iterations": 600.0, "work_evals": 600.0, "run_time": 0.002,
           "run_time_low": 0.0015, "run_time_high": 0.004, "timing_repeats": 30, "compile_time": 2.0,
           "energy_error": 3e-5, "pi3_error": 1e-13, "orthogonality_error": 1e-14, "position_error_final": 9e-3,
           "position_error_max": 1e-2, "attitude_error_final": 0.2, "attitude_error_max": 0.2, "t_reached": 2.0,
           "implementation": "jax-compiled", "load_avg": 2.5, "us_per_eval": 6.7, "flops": 1.2e7, **values}
    return runner.finish_row(row, f"key-{scene}-{setting}")


def table_bytes(rows) -> bytes:
    from reelbench.benchmark.runs import runner

    return runner.runs_frame(rows).to_csv(index=False).encode()


def many_rows(n=160) -> list[dict]:
    return [stored_row(setting=f"dt={0.01 / (k + 1):.6g}", dt=0.01 / (k + 1), steps=200 * (k + 1),
                       position_error_final=9e-3 / (k + 1) ** 2) for k in range(n)]


def _with_stray_byte(data: bytes) -> bytes:
    lines = data.split(b"\n")
    lines[5] = lines[5].replace(b",ok,", b",ok\xff,", 1)  # one non-UTF-8 byte in one row
    return b"\n".join(lines)


@pytest.mark.parametrize("content, why, kept", [
    (lambda: _with_stray_byte(table_bytes(many_rows())), "a byte that is not UTF-8", 159),
    (lambda: b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)), "not UTF-8", 0),
    (lambda: b"", "empty", 0),
    (lambda: b"name,price\nwidget,3\n", "not a runs table: no column(s) scene, integrator, setting, status", 0),
    (lambda: table_bytes(many_rows(3) + many_rows(1)), "1 row(s) repeat", 3),
], ids=["a stray byte", "binary", "empty", "foreign", "an exact repeat"])
def test_a_table_that_cannot_be_read_whole_is_kept_intact_and_its_rows_salvaged(tmp_path, content, why, kept):
    from reelbench.benchmark.runs import table

    path = tmp_path / "runs.csv"
    data = content()
    path.write_bytes(data)
    said = []
    got = table.read_runs(path, log=said.append)
    assert len(got.rows) == kept and got.aside is not None and got.aside.read_bytes() == data
    assert got.aside.parent == tmp_path and got.aside.name.startswith("runs.unreadable-")
    (line,) = [s for s in said if "cannot be read whole" in s]
    assert why in line and f"kept {kept} trusted row(s)" in line and str(got.aside) in line, said
    assert path.read_bytes() == data  # nothing is removed until the run writes its table


def test_rows_that_repeat_with_different_values_are_caught_on_read_none_trusted(tmp_path):
    from reelbench.benchmark.runs import table

    path = tmp_path / "runs.csv"
    path.write_bytes(table_bytes(many_rows(2) + [stored_row(setting="dt=0.01", energy_error=5e-5)]))
    said = []
    got = table.read_runs(path, log=said.append)
    assert [r["setting"] for r in got.rows] == ["dt=0.005"] and len(got.rejected) == 2, got.rejected
    assert all("appears 2 times with different values (lines 2, 4)" in why for _, why in got.rejected)
    assert got.aside is not None and got.aside.is_file()


def test_a_sweep_into_a_table_with_a_stray_byte_keeps_its_other_rows(tmp_path, capsys):
    """160 rows of another scene and one non-UTF-8 byte once left 3 rows and no copy."""
    import pandas as pd

    out = tmp_path / "out"
    out.mkdir()
    data = _with_stray_byte(table_bytes(many_rows()))
    (out / "runs.csv").write_bytes(data)
    rc = main(TINY + ["--dts", "0.01", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 0, err
    (aside,) = out.glob("runs.unreadable-*.csv")
    assert aside.read_bytes() == data
    said = [s for s in err.splitlines() if "cannot be read whole" in s]
    assert len(said) == 1 and "kept 159 trusted row(s)" in said[0] and "the other 1 are in that copy" in said[0]
    table = pd.read_csv(out / "runs.csv")
    assert len(table) == 160 and (table["scene"] == "deployment").sum() == 159


@pytest.mark.parametrize("edit", [
    {"run_time": 1e-9, "run_time_low": 1e-9, "run_time_high": 1e-9}, {"flops": 1.0}, {"us_per_eval": 1e-6},
    {"compile_time": 0.0}, {"energy_error": 1e-12},
], ids=["run times", "flops", "us_per_eval", "compile_time", "energy_error"])
def test_every_column_a_conclusion_reads_is_covered_by_the_digest(tmp_path, edit):
    from reelbench.benchmark.runs import table

    rows = many_rows(2)
    path = tmp_path / "runs.csv"
    path.write_bytes(table_bytes([{**rows[0], **edit}, rows[1]]))
    got = table.read_runs(path)
    assert len(got.rows) == 1 and "do not match the digest" in got.rejected[0][1], got.rejected


def test_a_row_whose_digest_was_blanked_is_tampered(tmp_path):
    from reelbench.benchmark.runs import table

    rows = many_rows(3)
    path = tmp_path / "runs.csv"
    path.write_bytes(table_bytes([{**rows[0], "row_digest": "", "energy_error": 1e-12}, *rows[1:]]))
    got = table.read_runs(path)
    assert len(got.rows) == 2 and not got.legacy
    assert "no row digest, where the table's other rows have one" in got.rejected[0][1]


def test_rows_from_before_digests_need_an_explicit_one_time_accept_legacy(tmp_path, capsys):
    import pandas as pd

    from reelbench.benchmark.runs import table

    out = tmp_path / "out"
    out.mkdir()
    legacy = pd.read_csv(__import__("io").BytesIO(table_bytes(many_rows(3)))).drop(columns=["row_digest"])
    legacy.to_csv(out / "runs.csv", index=False)
    before = (out / "runs.csv").read_bytes()
    rc = main(TINY + ["--dts", "0.01", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 2 and "3 row(s) this run keeps predate row digests" in line and "--accept-legacy" in line, err
    assert (out / "runs.csv").read_bytes() == before
    rc = main(TINY + ["--dts", "0.01", "--out", str(out), "--accept-legacy"])
    err, line = outcome(capsys)
    assert rc == 0 and "3 of them predate row digests: accepted by --accept-legacy" in err, err
    again = table.read_runs(out / "runs.csv")  # one time: they now carry digests
    assert len(again.rows) == 4 and not again.legacy and not again.rejected


# ------------------------------------------------------------------------------------------
# Edges of the stop signals and the output lock
# ------------------------------------------------------------------------------------------
def test_a_row_printed_as_finished_is_already_on_disk():
    from reelbench.benchmark.core import engine

    events = []
    p = engine.Progress(2, on_row=lambda rows: events.append(("saved", len(rows))),
                        log=lambda line: events.append(("printed", line)))
    p.done(1, {"x": 1})
    p.done(0, {"x": 0})
    assert [e[0] for e in events] == ["saved", "printed", "saved", "printed"], events
    assert events[0] == ("saved", 1) and events[1][1].startswith("[1/2]")


def test_temporaries_left_by_a_killed_run_are_removed_under_the_lock_and_only_stale_ones(tmp_path):
    import time

    from reelbench.benchmark.core import store

    (tmp_path / "cache").mkdir()
    stale = [tmp_path / ".runs.csv.k9ab_x12.tmp.csv", tmp_path / "cache" / ".reference-a-1.npz.zz99yy88.tmp.npz"]
    live = tmp_path / ".runs.md.abcdefgh.tmp.md"  # being written right now
    other = [tmp_path / "notes.tmp.csv", tmp_path / ".hidden.csv"]
    for p in stale + [live] + other:
        p.write_text("x")
    old = time.time() - 3600
    for p in stale + other:
        os.utime(p, (old, old))
    said = []
    with store.OutputLock(tmp_path, log=said.append):
        assert not any(p.exists() for p in stale) and live.exists() and all(p.exists() for p in other)
    assert any("removed 2 temporary file(s)" in s for s in said), said


def test_a_lock_that_cannot_be_written_is_the_cannot_write_line_and_leaves_no_lock(tmp_path, monkeypatch, capsys):
    from reelbench.benchmark.core import store

    real = os.open

    def read_only(path, *a, **k):
        if str(path).endswith(store.OutputLock.NAME):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(store.os, "open", read_only)
    out = tmp_path / "out"
    rc = main(TINY + ["--dts", "0.01", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 1 and line.startswith(f"error: cannot write {out / store.OutputLock.NAME}: Read-only file system"), err
    assert not (out / store.OutputLock.NAME).exists()


@pytest.mark.parametrize("sig, rc, name", [(2, 130, "Ctrl-C"), (15, 143, "SIGTERM")], ids=["SIGINT", "SIGTERM"])
def test_a_signal_in_the_first_moments_is_one_line_without_a_traceback(sig, rc, name):
    """Sent while the command line is still importing (it installs its handlers after): Ctrl-C
    printed a KeyboardInterrupt traceback, SIGTERM ended the process without a word. The clock
    starts once the package `benchmark` is imported (the interpreter's own start, `site`
    included, is not reelbench's code and takes from 20 ms to most of a second on a loaded
    machine): a thread of the child says when."""
    import subprocess
    import sys
    import time

    start = ("import runpy, sys, threading, time\nsys.argv = ['benchmark', 'list']\n"
             "def watch():\n    while 'benchmark' not in sys.modules:\n        time.sleep(0.0005)\n"
             "    print('started', flush=True)\n"
             "threading.Thread(target=watch, daemon=True).start()\n"
             "runpy.run_module('benchmark', run_name='__main__', alter_sys=True)\n")
    stopped = 0
    for delay in (0.03, 0.06, 0.1, 0.15):
        proc = subprocess.Popen([sys.executable, "-c", start], cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert proc.stdout.readline() == "started\n"
        time.sleep(delay)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
        assert "Traceback" not in err, (delay, err)
        if proc.returncode == 0:  # finished before the signal
            continue
        assert proc.returncode == rc and err.strip().splitlines()[-1].startswith(f"stopped by {name}"), (delay, err)
        stopped += 1
    assert stopped, "every run finished before its signal: nothing was tested"


# ------------------------------------------------------------------------------------------
# Links inside --out, and input quoted in an error line
# ------------------------------------------------------------------------------------------
def test_a_link_planted_inside_out_may_not_lead_out_of_it(tmp_path, capsys):
    """OUT/work_precision_fixed_length.png planted as a link to a file elsewhere: the figure is
    refused, nothing is written there, and the finished rows are kept."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    (out / "work_precision_fixed_length.png").symlink_to(elsewhere / "evil.png")
    rc = main(WITH_FIGURES + ["--dts", "0.01", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 2 and "leads outside" in line and "a link inside it may not lead out of it" in line, err
    assert list(elsewhere.iterdir()) == []
    assert len(__import__("pandas").read_csv(out / "runs.csv")) == 1  # the finished row is kept
    assert not (out / ".reelbench.lock").exists()


def test_a_link_inside_out_that_stays_inside_is_written_through(tmp_path):
    out = tmp_path / "out"
    (out / "real_cache").mkdir(parents=True)
    (out / "cache").symlink_to(out / "real_cache", target_is_directory=True)
    assert model_io.inside(out, "cache") == (out / "real_cache").resolve()


def test_error_lines_show_nul_bidi_overrides_and_newlines_escaped(tmp_path, capsys):
    assert model_io.printable("a\x00b\u202ec\nd, é π ×") == "a\\x00b\\u202ec\\nd, é π ×"
    hostile = tmp_path / "evil\u202e\nlmth.toml"
    rc = main(["simulate", str(hostile), "--dt", "0.01"])
    err, line = outcome(capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    # a scene error quotes the path TOML-style (\u000a), the other lines Python-style (\n): both one line
    assert any(f"evil\\u202e{nl}lmth.toml" in line for nl in ("\\n", "\\u000a")) and "\u202e" not in err, err
    rc = main(["simulate", "fixed_length", "--set", 'name="a\\u0000b"', "--dt", "0.01"])
    err, line = outcome(capsys)
    assert rc == 2 and "\x00" not in err and len(err.strip().splitlines()) == 1, err


# ------------------------------------------------------------------------------------------
# A failure is a nonzero exit, or a refusal in one line
# ------------------------------------------------------------------------------------------
WITH_FIGURES = [a for a in TINY if a != "--no-figures"]


def test_an_energy_study_too_long_to_run_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    from reelbench.benchmark.studies import grid

    monkeypatch.setattr(grid, "run_sweep", lambda *a, **k: pytest.fail("started the sweep"))
    rc = main(WITH_FIGURES + ["--dts", "0.01", "--horizon", "1e9", "--out", str(tmp_path / "o")])
    err, line = outcome(capsys)
    assert rc == 2 and "--horizon 1e+09: the energy study of lgvi at N = 1 would keep" in line, err
    assert "of trajectory in memory (limit 8 GiB): shorten --horizon" in line, err
    assert not (tmp_path / "o").exists()


def test_an_energy_study_whose_worker_crashed_ends_with_exit_1(tmp_path, monkeypatch, capsys):
    """It logged `horizon lgvi dt=0.005 [crashed]` and then exited 0."""
    from reelbench.benchmark.studies import horizon

    def crashed(job):
        return horizon.crash_row(job, MemoryError("out of memory"))

    monkeypatch.setattr(horizon, "run_job", crashed)
    out = tmp_path / "o"
    rc = main(WITH_FIGURES + ["--dts", "0.01", "--horizon", "0.1", "--out", str(out)])
    err, line = outcome(capsys)
    assert rc == 1, err
    assert line.startswith("error: the energy study did not finish for lgvi dt=") and "N=1 on fixed_length" in line, err
    assert "(MemoryError: out of memory)" in line, err
    assert len(__import__("pandas").read_csv(out / "runs.csv")) == 1  # the runs table is complete


def test_reel_reversal_on_a_scene_without_a_reel_is_refused(tmp_path, capsys):
    rc = main(["reel-reversal", "--scenes", "fixed_length", "--cache-dir", str(tmp_path / "c")])
    err, line = outcome(capsys)
    assert rc == 2 and "'fixed_length' has no reel" in line and "--scenes reel_reversal" in line, err
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("damage, fragment", [
    (lambda meta, arrays: meta.update(status=123), "status 123, which is not a status a run ends with"),
    (lambda meta, arrays: meta.update(status="bogus"), "status 'bogus'"),
    (lambda meta, arrays: arrays["x"].__setitem__((1, 0), np.inf), "its x array holds 1 value(s) that are not finite"),
    (lambda meta, arrays: arrays["t"].__setitem__(-1, np.nan), "its t array holds 1 value(s)"),
], ids=["status 123", "status bogus", "an inf in the state", "a nan time"])
def test_figures_refuse_a_trajectory_that_simulate_did_not_write(tmp_path, capsys, damage, fragment):
    import json

    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene

    traj = get_integrator("lgvi").solve(load_scene("fixed_length", elements=1), t_end=0.04, dt=0.01)
    traj.save(tmp_path / "t.npz")
    with np.load(tmp_path / "t.npz") as data:
        arrays = {k: np.array(data[k]) for k in data.files if k != "meta"}
        meta = json.loads(str(data["meta"]))
    damage(meta, arrays)
    np.savez(tmp_path / "bad.npz", meta=np.array(json.dumps(meta)), **arrays)
    rc = main(["figures", str(tmp_path / "bad.npz"), "--set", "elements=1", "--out", str(tmp_path / "f.png")])
    err, line = outcome(capsys)
    assert rc == 2 and fragment in line, err
    assert not (tmp_path / "f.png").exists()


def test_the_step_limit_is_at_most_1e9_planned_steps_in_the_command_line_and_the_integrators():
    """Exactly 1e9 steps is allowed and one more refused, by the same count (the loop's)."""
    from reelbench.benchmark.core import options
    from reelbench.integrators import lifecycle
    from reelbench.models import load_scene

    scene = load_scene("fixed_length", elements=1)
    dt = 2.0 ** -20  # t_end / dt exact
    for steps, allowed in ((10 ** 9, True), (10 ** 9 + 1, False)):
        t_end = steps * dt
        if allowed:
            assert options.check_size(scene, t_end, t_end, dt)["steps"] == steps
            lifecycle.check_horizon(scene, "fixed", t_end, dt, t_end)
        else:
            with pytest.raises(options.UsageError, match="1000000001 steps .*allowed: at most 1e[+]09 planned steps"):
                options.check_size(scene, t_end, t_end, dt)
            with pytest.raises(ValueError, match="allowed: at most 1e[+]09"):
                lifecycle.check_horizon(scene, "fixed", t_end, dt, t_end)
