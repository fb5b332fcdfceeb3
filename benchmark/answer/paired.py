"""Wall-time verdicts from paired, interleaved timing.

Single run times of a few ms move by a factor 2 between sweeps on a shared machine, but the ratio
of two methods timed *in turn*, round after round on one core, is far steadier: the load that
slows one solve slows its neighbour in the same round too. So the candidates at a target (each at
its own setting there) are timed round-robin: every round runs each method once, in an order
that rotates from round to round; the ratio of a method to the reference (the fastest by median
time) is the median over rounds of its time / the reference's time in the same round; its 90 %
interval is a bootstrap over rounds (rounds resampled with replacement, the pairing kept). The
reference is the fastest by paired ratio.

Rounds are added until every ratio's interval lies within ±``precision`` (10 %) of the ratio, or
the time budget of the target (`BUDGET`, 20 s of timing) ends. The timing races: from
`RACE_ROUNDS` rounds on, a method whose interval lies wholly above 1 + `RACE_MARGIN` (clearly
slower than the margin that makes a tie) leaves, so the rounds go to the contenders; it keeps
the ratio, interval and ``slower`` verdict it left with (a bootstrap of its few rounds against
a reference chosen later could read as a tie it had already been shown out of). The verdict comes from the
intervals: the fastest method is the ``winner`` only when every other method's interval lies
above 1 + `EQUIVALENCE`; otherwise it and every method whose interval reaches that are a
``tie``; the rest are ``slower``. The margin is measured, not chosen: a pass's bootstrap interval
sees the noise within that pass, but two passes of the same settings in separate processes (each
compiles its own programs) moved a ratio by up to 11 % (median 2 %) on a quiet pinned core, so a
method 9 % slower with an interval of [1.06, 1.16] in one pass was the fastest in the next.

Pure apart from the clock and the callables it is given: each ``solve()`` returns the seconds
of one whole solve (compilation excluded: `integrators.base.stamp_wall_time`). `pinned` puts
the calling process on one core for the duration.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from reelbench.benchmark.core.policy import PAIRED_BUDGET, RESOLUTION, SLOWER, TIE, TIE_MARGIN, WINNER

#: Seconds of timing per target (all methods' solves together, the setup excluded).
BUDGET = PAIRED_BUDGET
#: The interval must lie within this relative distance of the ratio for timing to stop early.
PRECISION = RESOLUTION
#: The interval's coverage (two-sided), and the bootstrap's resamples.
LEVEL = 0.90
RESAMPLES = 2000
#: Ratios this close to 1 are a tie whatever their interval (the module's docstring): the largest
#: change of a ratio between two quiet timing passes of the 12 committed targets was 10.7 %.
EQUIVALENCE = TIE_MARGIN
#: Rounds before the first stop check (a bootstrap of fewer is not an interval), and at most.
MIN_ROUNDS = 8
#: The race: from this many rounds on, a method whose interval's lower end is above 1 + RACE_MARGIN
#: leaves (twice the tie margin: a method that leaves can never be part of a tie).
RACE_ROUNDS = 4
RACE_MARGIN = 2 * TIE_MARGIN
MAX_ROUNDS = 2000


@dataclass
class Ratio:
    """One method against the reference: the median of paired ratios, its bootstrap interval,
    the number of pairs and the verdict."""

    method: str
    time: float  # median seconds of one solve
    ratio: float
    low: float
    high: float
    pairs: int
    verdict: str = ""


def ratio_interval(mine: np.ndarray, ref: np.ndarray, rng: np.random.Generator, level: float = LEVEL,
                   resamples: int = RESAMPLES) -> tuple[float, float, float]:
    """(median of mine / ref per round, the bootstrap interval of that median at ``level``).
    Percentile, not BCa: the interval is the spread of the median over resampled rounds, and
    BCa's jackknife of a median over a few rounds (4 at the first race check) is degenerate."""
    from scipy.stats import bootstrap

    r = np.asarray(mine, float) / np.asarray(ref, float)
    if len(r) < 2:
        return float(np.median(r)), 0.0, np.inf
    ci = bootstrap((r,), np.median, n_resamples=resamples, confidence_level=level, method="percentile",
                   rng=rng).confidence_interval
    return float(np.median(r)), float(ci.low), float(ci.high)


def verdicts(ratios: list[Ratio], equivalence: float = EQUIVALENCE) -> list[Ratio]:
    """Set each `Ratio`'s verdict in place (module docstring) and return them, fastest first."""
    ratios = sorted(ratios, key=lambda r: (r.ratio, r.method))
    best, others = ratios[0], ratios[1:]
    alone = all(o.low > 1.0 + equivalence for o in others)
    best.verdict = WINNER if alone else TIE
    for o in others:
        o.verdict = SLOWER if o.low > 1.0 + equivalence else TIE
    return ratios


def compare(ratios_of: dict[str, np.ndarray], rng: np.random.Generator, level: float = LEVEL) -> list[Ratio]:
    """The ratios of every method to the fastest (by median) from the rounds' times. A method
    that left the race has fewer rounds: it is paired with the reference's first rounds, the ones
    it ran beside; the reference is chosen among the methods that ran every round."""
    times = {m: np.asarray(t, float) for m, t in ratios_of.items()}
    full = max(len(t) for t in times.values())
    racing = sorted(m for m, t in times.items() if len(t) == full)
    base = racing[0]
    # the reference: the fastest by paired ratio (to any one method), not by median time, so that
    # no other method's median ratio to it falls below 1 where the pairing says otherwise
    ref = min(racing, key=lambda m: (float(np.median(times[m] / times[base])), m))
    out = []
    for m, t in times.items():
        ratio, lo, hi = (1.0, 1.0, 1.0) if m == ref else ratio_interval(t, times[ref][: len(t)], rng, level)
        out.append(Ratio(m, float(np.median(t)), ratio, lo, hi, len(t)))
    return verdicts(out)


def leaving(ratios: list[Ratio], margin: float = RACE_MARGIN) -> list[str]:
    """The methods clearly slower than the tie margin: their whole interval above 1 + ``margin``."""
    return [r.method for r in ratios if r.low > 1.0 + margin]


def resolved(ratios: list[Ratio], precision: float = PRECISION) -> bool:
    """Every ratio's interval lies within ±precision of the ratio."""
    return all(r.low >= r.ratio * (1 - precision) and r.high <= r.ratio * (1 + precision) for r in ratios)


def time_paired(solves: dict[str, Callable[[], float]], *, budget: float = BUDGET, precision: float = PRECISION,
                level: float = LEVEL, min_rounds: int = MIN_ROUNDS, max_rounds: int = MAX_ROUNDS, seed: int = 0,
                race_rounds: int = RACE_ROUNDS, race_margin: float = RACE_MARGIN,
                clock: Callable[[], float] = time.perf_counter,
                progress: Callable[[int, float, list[Ratio]], None] | None = None) -> list[Ratio]:
    """Time ``solves`` (method -> a callable returning one solve's seconds) round-robin until
    `resolved` or ``budget`` seconds of timing have passed (``max_rounds`` at most), the clearly
    slower ones leaving the race from ``race_rounds`` rounds on (`leaving`); the ratios and
    verdicts, fastest first. One method alone is its own ``winner`` (ratio 1).
    ``progress(rounds, seconds, ratios)`` is called after every stop check."""
    if not solves:
        raise ValueError("time_paired: no methods to time")
    names = sorted(solves)
    rng = np.random.default_rng(seed)
    times: dict[str, list[float]] = {m: [] for m in names}
    racing = list(names)
    left: dict[str, Ratio] = {}  # the methods that left the race, as they left it
    started = clock()
    rounds = 0
    ratios: list[Ratio] = []

    def current() -> list[Ratio]:
        return verdicts(compare({m: times[m] for m in racing}, rng, level) + list(left.values()))

    while rounds < max_rounds:
        for k in range(len(racing)):  # rotate who goes first: no method always follows another
            m = racing[(rounds + k) % len(racing)]
            times[m].append(float(solves[m]()))
        rounds += 1
        if len(racing) > 1 and rounds >= race_rounds:
            now = compare({m: times[m] for m in racing}, rng, level)
            gone = set(leaving(now, race_margin))
            left.update({r.method: r for r in now if r.method in gone})
            racing = [m for m in racing if m not in gone]
        if rounds >= min_rounds or len(names) == 1:
            ratios = current()
            if progress:
                progress(rounds, clock() - started, ratios)
            contenders = [r for r in ratios if r.method in racing]
            if len(names) == 1 or resolved(contenders, precision) or clock() - started >= budget:
                break
    return ratios or current()


@contextlib.contextmanager
def pinned(core: int | None = None):
    """This process on one core (the last one it may use, or ``core``) for the duration, where
    the platform allows it; the old affinity restored after."""
    if not hasattr(os, "sched_setaffinity"):
        yield None
        return
    old = os.sched_getaffinity(0)
    core = max(old) if core is None else core
    try:
        os.sched_setaffinity(0, {core})
    except OSError:
        yield None
        return
    try:
        yield core
    finally:
        os.sched_setaffinity(0, old)
