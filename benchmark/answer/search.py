"""The cheapest setting that meets a target and stands when moved, found by search instead of read
off a fixed grid.

Pure: `search` takes a callable ``run(setting) -> (status, error, cost)`` (one solve of one
method on one scene at a step size or tolerance) and calls it until it knows, within a run
budget, the cheapest setting that meets the target. Nothing here solves, times or writes.

A setting is a positive number; larger is *coarser* (a larger step or a looser tolerance),
cheaper, and less accurate or less likely to finish. Settings lie on a lattice, ``start ·
grid^k`` for whole k (`GRID`: 2^(1/8) for a step, 10^(1/8) for a tolerance), so that two
settings a user would call neighbours are neighbours here. The search:

1. **brackets** the target from the start setting: coarser by ``factor`` (whole lattice steps)
   while the setting meets the target (status ``ok`` and error <= target), finer while it does
   not, until one setting meets the target and the next coarser one does not, or a limit of the
   setting's range, or the budget;
2. **bisects** the bracket on the lattice until its two ends are neighbours or within
   ``resolution`` (10 %) of each other in cost;
3. **confirms** it: a setting *stands* only when the `CONFIRM` settings just finer on the lattice
   meet the target too. Where one does not (an adaptive method's error is erratic where its step
   is held by stability, not by accuracy), the search goes on below the one that missed until a
   setting stands. A setting that met the target above the answer without standing is named in
   ``erratic_above``.

``bound`` says what limits the answer: ``target`` (the coarser end finished but missed the
target), ``stability`` (the coarser end did not finish: the stability boundary, located to the
same 10 %), ``largest setting`` (the coarsest allowed setting meets it: nothing cheaper exists to
find), ``budget`` (the runs ran out first, or a run hit its own step or time budget, after which
the search goes no finer; the row keeps the best setting reached, ``confirmed`` False where it
could not be confirmed), ``not reached``.

**The answer never extrapolates:** it is the cheapest *measured* setting that stands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

from reelbench.benchmark.core.policy import NOT_REACHED, RESOLUTION  # two settings this close in cost are close enough (the 10 %)

#: What limits a search's answer (its ``bound``; see the module's docstring), besides `NOT_REACHED`.
TARGET, STABILITY, LARGEST_SETTING, BUDGET = "target", "stability", "largest setting", "budget"

#: The most runs of one search (bracket, bisection and confirmation together).
MAX_RUNS = 24
#: The lattice ratio of each axis: a step on the 2^(1/8) grid, a tolerance on the 1/8-decade grid.
GRID = {"dt": 2.0 ** 0.125, "rtol": 10.0 ** 0.125}
#: How many settings just finer than an answer must meet the target too for it to stand.
CONFIRM = 3


@dataclass(frozen=True)
class Point:
    """One run of the search: its setting, status, error (NaN without one) and cost."""

    setting: float
    status: str
    error: float
    cost: float

    @property
    def finished(self) -> bool:
        from reelbench.integrators.base import is_finished  # here: the command line imports this module at start

        return is_finished(self.status) and math.isfinite(self.error)

    def meets(self, target: float) -> bool:
        return self.finished and self.error <= target


@dataclass
class Found:
    """The outcome of one search (see the module's docstring)."""

    target: float
    bound: str
    setting: float = math.nan  # the answer: the cheapest measured setting that stands
    cost: float = math.nan
    error: float = math.nan
    setting_low: float = math.nan  # the bracket's finer end (meets the target): the answer
    setting_high: float = math.nan  # its coarser end (missed, failed, or nan at a range limit)
    setting_finer: float = math.nan  # the measured neighbour finer than the answer, if any
    high_status: str = ""  # the coarser end's status ("ok": it finished and missed the target)
    non_monotone: bool = False  # a coarser setting met the target where a finer one missed it
    confirmed: bool = False  # the CONFIRM settings just finer met the target too
    erratic_above: float = math.nan  # the coarsest setting above the answer that met it without standing
    points: list[Point] = field(default_factory=list)

    @property
    def runs(self) -> int:
        return len(self.points)

    @property
    def spread(self) -> float:
        """cost(answer) / cost(coarser end) - 1 where both are measured (else the settings' ratio - 1)."""
        lo, hi = self._at(self.setting_low), self._at(self.setting_high)
        if lo is None or hi is None:
            return math.nan
        if _costed(lo) and _costed(hi):
            return lo.cost / hi.cost - 1.0
        return hi.setting / lo.setting - 1.0

    def _at(self, s: float) -> Point | None:
        return next((p for p in self.points if p.setting == s), None)


def _costed(p: Point) -> bool:
    from reelbench.integrators.base import is_finished

    return is_finished(p.status) and math.isfinite(p.cost) and p.cost > 0


def _stopped_by_budget(status: str) -> bool:
    """A run stopped by its own budget (`integrators.base.BUDGET_STATUSES`: steps, seconds): a finer
    setting costs more, so the search goes no finer after one (its bound is then ``budget``)."""
    from reelbench.integrators.base import BUDGET_STATUSES  # here: the command line imports this module at start

    return status in BUDGET_STATUSES


def close(good: Point, bad: Point, resolution: float = RESOLUTION) -> bool:
    """The bracket (``good`` meets the target, ``bad`` is coarser and does not) is resolved: its
    ends are within ``resolution`` in cost (in setting where ``bad`` has no cost)."""
    if _costed(good) and _costed(bad):
        return good.cost <= bad.cost * (1.0 + resolution)
    return bad.setting <= good.setting * (1.0 + resolution)


class _Lattice:
    """Settings start·grid^k for whole k in [k_min, k_max] (the range's lattice points)."""

    def __init__(self, start: float, lowest: float, highest: float, grid: float):
        self.start, self.log = start, math.log(grid)
        self.k_min = math.ceil(math.log(lowest / start) / self.log - 1e-9)
        self.k_max = math.floor(math.log(highest / start) / self.log + 1e-9)

    def setting(self, k: int) -> float:
        return float(self.start * math.exp(k * self.log)) if k else float(self.start)

    def index(self, s: float) -> int:
        return round(math.log(s / self.start) / self.log)


def search(run: Callable[[float], tuple[str, float, float]], target: float, start: float, *, lowest: float,
           highest: float, factor: float = 2.0, grid: float | None = None, resolution: float = RESOLUTION,
           max_runs: int = MAX_RUNS, confirm: int = CONFIRM,
           known: dict[float, tuple[str, float, float]] | None = None) -> Found:
    """The cheapest setting on the lattice in [lowest, highest] at which ``run`` meets ``target``
    and that stands (module docstring). ``grid``: the lattice ratio (default ``factor``^(1/8));
    ``known``: results of settings run before, used instead of running them again (they count
    against ``max_runs``)."""
    if not (0 < lowest <= start <= highest) or not all(math.isfinite(v) for v in (lowest, start, highest)):
        raise ValueError(f"search: need 0 < lowest <= start <= highest (got {lowest!r}, {start!r}, {highest!r})")
    if not (factor > 1 and math.isfinite(factor)):
        raise ValueError(f"search: factor = {factor!r} is invalid (allowed: a finite number > 1)")
    if not (target > 0 and math.isfinite(target)):
        raise ValueError(f"search: target = {target!r} is invalid (allowed: a finite number > 0)")
    grid = factor ** 0.125 if grid is None else grid
    if not (1 < grid <= factor):
        raise ValueError(f"search: grid = {grid!r} is invalid (allowed: 1 < grid <= factor)")
    lat = _Lattice(start, lowest, highest, grid)
    jump = max(1, round(math.log(factor) / lat.log))
    known = dict(known or {})
    points: dict[int, Point] = {}

    def at(k: int) -> Point:
        if k not in points:
            s = lat.setting(k)
            status, error, cost = known[s] if s in known else run(s)
            points[k] = Point(s, str(status), float(error), float(cost))
        return points[k]

    def budget_left() -> bool:
        return len(points) < max_runs

    good = bad = None  # lattice indices
    if at(0).meets(target):
        good = 0
        while budget_left() and good < lat.k_max:  # coarser until missed or failed
            k = min(good + jump, lat.k_max)
            if at(k).meets(target):
                good = k
            else:
                bad = k
                break
    else:
        bad = 0
        while budget_left():  # finer until met, never past a run stopped by its own budget
            if bad <= lat.k_min or _stopped_by_budget(at(bad).status):
                break
            k = max(bad - jump, lat.k_min)
            if at(k).meets(target):
                good = k
                break
            bad = k
    if good is not None and bad is not None:
        while bad - good > 1 and not close(at(good), at(bad), resolution) and budget_left():
            k = (good + bad) // 2
            if at(k).meets(target):
                good = k
            else:
                bad = k
    if good is not None:
        _confirm(at, good, lat.k_min, confirm, target, budget_left)
    return _found(points, target, lat, resolution, confirm)


def _confirm(at, k: int, k_min: int, confirm: int, target: float, budget_left) -> None:
    """Run the settings just finer than ``k`` until one stands: where one of them misses the
    target, go on below it. Stops at the range's end, at a run stopped by its own budget, or when
    the runs run out."""
    while budget_left():
        missed = None
        for j in range(1, confirm + 1):
            if k - j < k_min or not budget_left():
                return
            p = at(k - j)
            if _stopped_by_budget(p.status):
                return
            if not p.meets(target):
                missed = k - j
                break
        if missed is None:
            return
        k = missed - 1
        if k < k_min:
            return
        while budget_left() and k >= k_min and not at(k).meets(target):  # down to the next setting that meets it
            if _stopped_by_budget(at(k).status):
                return
            k -= 1


def _stands(points: dict[int, Point], k: int, lat: _Lattice, confirm: int, target: float) -> bool:
    """The point at k meets the target, and so do the ``confirm`` lattice settings just finer
    (those below the range's end need not exist)."""
    return points[k].meets(target) and all(
        k - j < lat.k_min or (k - j in points and points[k - j].meets(target)) for j in range(1, confirm + 1))


def _found(points: dict[int, Point], target: float, lat: _Lattice, resolution: float, confirm: int) -> Found:
    ks = sorted(points)
    plist = [points[k] for k in ks]
    meeting = [k for k in ks if points[k].meets(target)]
    if not meeting:  # the finest setting allowed missed it too, or the runs (or a run's own budget) ran out
        finest = points[ks[0]]
        return Found(target, NOT_REACHED if ks[0] <= lat.k_min and not _stopped_by_budget(finest.status)
                     else BUDGET, setting_high=finest.setting, high_status=finest.status, points=plist)
    standing = [k for k in meeting if _stands(points, k, lat, confirm, target)]

    def cheapest(ks_):  # the cheapest by cost, the coarsest on ties
        return max(ks_, key=lambda k: (-(points[k].cost if _costed(points[k]) else math.inf), k))

    best = cheapest(standing) if standing else cheapest(meeting)
    i = ks.index(best)
    coarser = points[ks[i + 1]] if i + 1 < len(ks) else None
    finer = points[ks[i - 1]] if i > 0 else None
    unstable = [k for k in meeting if k > best and not _stands(points, k, lat, confirm, target)]
    p = points[best]
    out = Found(target, "", setting=p.setting, cost=p.cost, error=p.error, setting_low=p.setting,
                setting_high=coarser.setting if coarser else math.nan,
                setting_finer=finer.setting if finer else math.nan,
                high_status=coarser.status if coarser else "",
                non_monotone=any(k < best and not points[k].meets(target) for k in ks) or bool(unstable),
                confirmed=bool(standing), erratic_above=points[max(unstable)].setting if unstable else math.nan,
                points=plist)
    if not standing:
        out.bound = BUDGET
    elif coarser is None:
        out.bound = LARGEST_SETTING if best >= lat.k_max else BUDGET
    elif coarser.meets(target):  # a coarser setting met it without standing, or at a higher cost
        out.bound = TARGET
    elif not close(p, coarser, resolution) and ks[i + 1] - best > 1:
        out.bound = BUDGET
    else:
        out.bound = TARGET if coarser.finished else STABILITY
    return out
