"""Checks of command-line input that need no JAX: option types and ranges, output places,
and a size estimate of a run. Everything here answers in milliseconds, so that the command
line refuses nonsense before it imports the model (`benchmark.cli.main`).

Type functions (`positive_int`, `float_list`, ...) are argparse ``type=`` callables: argparse
names the option in its message ("argument --jobs: ...") and exits with status 2.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from pathlib import Path

from reelbench.benchmark.core.policy import ROW_IDENTITY, SOLVE_MAX_STEPS, SOLVE_TIME_LIMIT  # noqa: F401 (the budget defaults)


class UsageError(ValueError):
    """Bad input found before any work; the command line prints it as ``error: ...`` (exit 2)."""


def _number(text: str, kind=float) -> float:
    try:
        v = kind(text)
    except (TypeError, ValueError):
        what = "an integer (give one, e.g. 4)" if kind is int else "a number (give one, e.g. 0.01)"
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
    if kind is float and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number (give one, e.g. 0.01)")
    return v


def number(text: str) -> float:
    """A finite float (its range is checked where it is used)."""
    return _number(text)


def integer(text: str) -> int:
    """An integer (its range is checked where it is used)."""
    return _number(text, int)


def positive_int(text: str) -> int:
    v = _number(text, int)
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: an integer >= 1)")
    return v


def nonnegative_int(text: str) -> int:
    v = _number(text, int)
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: an integer >= 0)")
    return v


def positive_float(text: str) -> float:
    v = _number(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: a finite number > 0)")
    return v


def nonnegative_float(text: str) -> float:
    v = _number(text)
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: a finite number >= 0)")
    return v


def tolerance(text: str) -> float:
    from reelbench.integrators.lifecycle import MIN_RTOL, rtol_allowed  # the API's rule (imported only when one is given)

    v = _number(text)
    if not rtol_allowed(v):
        raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: {MIN_RTOL:g} <= tolerance < 1; "
                                         "tighter is below float64 rounding)")
    return v


def _list_of(item):
    def parse(text: str) -> list:
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"{text!r} is empty (allowed: comma-separated values, e.g. 0.01,0.005)")
        return [item(p) for p in parts]

    parse.__name__ = f"list of {item.__name__}"
    return parse


positive_floats = _list_of(positive_float)
positive_ints = _list_of(positive_int)
integers = _list_of(integer)
tolerances = _list_of(tolerance)


def check_factor(factor: float) -> None:
    """`check`'s --factor: finite, > 1; UsageError naming it."""
    if not (math.isfinite(factor) and factor > 1):
        raise UsageError(f"--factor = {factor!r} is invalid (allowed: finite, > 1; e.g. 2 = twice the baseline)")


def check_order_margin(order_margin: float) -> None:
    """`check`'s --order-margin: finite, >= 0; UsageError naming it."""
    if not (math.isfinite(order_margin) and order_margin >= 0):
        raise UsageError(f"--order-margin = {order_margin!r} is invalid (allowed: finite, >= 0; e.g. 0.5)")


def check_tolerance_rules(factor: float, order_margin: float) -> None:
    """`check`'s --factor (finite, > 1) and --order-margin (finite, >= 0); UsageError naming them."""
    check_factor(factor)
    check_order_margin(order_margin)


def csv_table(columns: tuple, what: str):
    """An argparse type: an existing CSV file whose header has ``columns`` (checked without pandas);
    ``what`` names the table a user should give."""
    def check(text: str) -> str:
        path = Path(text)
        if not path.is_file():
            raise argparse.ArgumentTypeError(f"{text!r} is not a file (allowed: {what})")
        try:
            with open(path, encoding="utf-8") as fh:
                header = fh.readline().strip().split(",")
        except (OSError, UnicodeDecodeError) as exc:
            raise argparse.ArgumentTypeError(f"{text!r} cannot be read ({exc})") from None
        missing = [c for c in columns if c not in header]
        if missing:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}: no column(s) {', '.join(missing)}")
        return text
    return check


#: The runs.csv of an earlier run (`run --compare-with`), and an earlier answer's cheapest.csv
#: (`answer --compare-with`).
runs_table = csv_table((*ROW_IDENTITY, "status", "run_time"), "the runs.csv of an earlier run")
answer_table = csv_table(("scene", "elements", "metric", "target", "cost_kind", "entry", "verdict", "ratio"),
                         "the cheapest.csv of an earlier answer")


def names(text: str) -> list[str]:
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if not parts:
        raise argparse.ArgumentTypeError(f"{text!r} is empty (allowed: comma-separated names)")
    return parts


def _nearest_existing(p: Path) -> Path:
    """``p`` or the closest of its parents that exists (where a missing directory would be made)."""
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def writable_dir(path: str | os.PathLike, option: str = "--out") -> Path:
    """Prove that ``path`` is, or can be created as, a directory that takes a file (a probe file
    written and deleted in it or in its nearest existing parent), or raise UsageError naming the
    option, the place and the fix. Nothing is created: a command refused by a later check leaves
    no empty --out behind (the study creates the directory when it starts writing)."""
    if not str(path).strip():
        raise UsageError(f"{option} is empty: give a directory (it is created if missing)")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{option} {str(p)!r} is a file, not a directory: give a directory (it is created if missing)")
    base = _nearest_existing(p.absolute())
    if not base.is_dir():
        raise UsageError(f"{option} {str(p)!r} is not writable ({base} is a file, not a directory): "
                         f"give a directory you can write to")
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=base)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UsageError(f"{option} {str(p)!r} is not writable ({exc.strerror or exc}): "
                         f"give a directory you can write to") from None
    return p


def no_directory_at(directory: Path, names, option: str = "--out") -> None:
    """Refuse a directory, or a FIFO, device or link to one, where a command reads back and
    writes one of its files ``names`` in ``directory``: reading a FIFO would block, a device
    read forever, and a directory fails only after the work, when the first result is written."""
    import stat

    for name in names:
        path = Path(directory) / name
        try:
            mode = path.stat().st_mode
        except OSError:  # missing (or a dangling link): written fresh
            continue
        if stat.S_ISREG(mode):
            continue
        what = "a directory" if stat.S_ISDIR(mode) else "not a regular file (a FIFO, device or socket)"
        raise UsageError(f"{option} {str(directory)!r}: {name} there is {what}, where this command writes a "
                         f"file: move it away, or give another {option}")


def writable_file(path: str | os.PathLike, option: str = "--out") -> Path:
    """A file path whose directory takes a file (created when the file is written); refuses an
    empty path and a directory."""
    if not str(path).strip():
        raise UsageError(f"{option} is empty: give a file name (e.g. run.npz)")
    p = Path(path)
    if p.is_dir():
        raise UsageError(f"{option} {str(p)!r} is a directory: give a file name (e.g. {p / 'run.npz'})")
    writable_dir(p.parent if str(p.parent) else ".", option=f"{option} (its directory)")
    return p


# --------------------------------------------------------------------------------------------
# Size of a run, before it starts
# --------------------------------------------------------------------------------------------
#: Warn when a run's saved trajectory would need more memory than this (bytes). A run is refused
#: beyond the integrators' own limits: `integrators.lifecycle.MAX_SAVED_BYTES` (of the size
#: `lifecycle.saved_size`) and `lifecycle.MAX_PLANNED_STEPS` (counted as the fixed-step loop runs:
#: `integrators.base.fixed_step_count`): exactly 1e9 steps run, one more is refused. At the
#: estimate below, 1e9 steps is over half an hour at N = 10 and days at N = 1000; below it the time
#: estimate warns instead.
MEMORY_WARN = 1 * 2**30
#: The refusal limits, the integrators' own (`integrators.lifecycle`), restated for the reason in
#: `run_size`; tests/test_policy.py pins them equal.
MEMORY_REFUSE = 8 * 2**30
STEPS_REFUSE = 1e9
#: Warn when the estimated wall time of one run exceeds this (s).
TIME_WARN = 600.0
#: LGVI time per step ≈ STEP_COST_10 × (N/10)^0.9 (results/lgvi_speed.md, one core: 1.07 µs on
#: fixed_length and 1.98 µs on deployment at N = 10, log-log slope 0.81–0.87); an estimate,
#: not a promise: the fourth-order variants cost 3–5x that per step, constant-step Tsit5 10–20x.
STEP_COST_10 = 2e-6


def run_size(scene, t_end: float, save_every: float, dt: float | None = None) -> dict:
    """Saved points, bytes of the saved trajectory and (fixed step) the steps and an estimated
    wall time of one run of ``scene``; no JAX needed."""
    from reelbench.models.layout import StateLayout  # JAX-free: the sizes the listed effects give

    # The integrators' own rules, restated: importing them would import the integrators package
    # (its registry) on every refusal. tests/test_policy.py pins both to them.
    lay = StateLayout.from_scene(scene)
    interval = save_every if dt is None else max(save_every, dt)  # lifecycle.saved_interval
    points = math.floor(t_end / interval) + 2
    size = points * 8 * (lay.nx + 2 * lay.nw + 9 + 2)  # lifecycle.saved_size: x, velocity, momentum, attitude, work, t
    out = {"points": points, "bytes": size, "steps": None, "seconds": None}
    if dt is not None:
        out["steps"] = max(1, math.ceil(t_end / dt - 1e-9))  # base.fixed_step_count: what the fixed-step loop runs
        out["seconds"] = out["steps"] * STEP_COST_10 * (scene.string.elements / 10.0) ** 0.9
    return out


def _human_bytes(b: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if b < 1024 or unit == "TiB":
            return f"{b:.3g} {unit}"
        b /= 1024
    return f"{b:.3g} TiB"  # pragma: no cover


def _human_seconds(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    if s < 2 * 86400:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.3g} days"


def check_size(scene, t_end: float, save_every: float, dt: float | None = None, *, warn=None,
               what: str = "this run", save_option: str | None = "--save-every", t_end_option: str = "--t-end") -> dict:
    """Refuse (UsageError) a run that cannot fit (memory, steps); warn through ``warn`` about a
    large one. ``save_option``: the option that sets the save interval, if the command has one
    (the fix a refusal names). Returns `run_size`."""
    size = run_size(scene, t_end, save_every, dt)
    mem = (f"{size['points']:,} saved points × {scene.string.elements} elements ≈ "
           f"{_human_bytes(size['bytes'])}")
    if size["bytes"] > MEMORY_REFUSE:
        raise UsageError(f"{what} would keep {mem} of trajectory in memory (limit {_human_bytes(MEMORY_REFUSE)}): "
                         + (f"raise {save_option}, " if save_option else "") + f"shorten {t_end_option} or use fewer "
                         "elements")
    if size["steps"] is not None and size["steps"] > STEPS_REFUSE:
        raise UsageError(f"{what} would take {size['steps']:.10g} steps of dt = {dt:g} s to t_end = {t_end:g} s "
                         f"(allowed: at most {STEPS_REFUSE:.0e} planned steps; estimated "
                         f"{_human_seconds(size['seconds'])}): raise --dt or shorten {t_end_option}")
    if warn is not None:
        if size["bytes"] > MEMORY_WARN:
            warn(f"warning: {what} will keep {mem} in memory")
        if size["seconds"] is not None and size["seconds"] > TIME_WARN:
            warn(f"warning: {what} takes {size['steps']:.3g} steps; estimated {_human_seconds(size['seconds'])} "
                 f"(at ~{STEP_COST_10 * 1e6 * (scene.string.elements / 10) ** 0.9:.0f} µs per step)")
    return size
