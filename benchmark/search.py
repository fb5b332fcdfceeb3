"""The cheapest setting that meets a target, found by search instead of read off a fixed grid.

Pure: `search` takes a callable ``run(setting) -> (status, error, cost)`` (one solve of one
method on one scene at a step size or tolerance) and calls it until it knows, within a run
budget, the cheapest setting that meets the target. Nothing here solves, times or writes.

A setting is a positive number; larger is *coarser* (a larger step or a looser tolerance),
cheaper, and less accurate or less likely to finish. The search:

1. **brackets** the target from the start setting: coarser by ``factor`` while the setting meets
   the target (status ``ok`` and error <= target), finer by ``factor`` while it does not, until
   one setting meets the target and the next coarser one does not (it missed the target or did
   not finish), or a limit of the setting's range, or the budget;
2. **bisects** the bracket in log setting (the geometric mean of its ends) until its two ends
   are within ``resolution`` (10 %) of each other in cost: both measured costs where both runs
   finished, else in the setting itself (a failed run has no cost: a fixed step's cost is
   inversely proportional to it, so this is the same criterion).

``bound`` says what limits the answer: ``target`` (the coarser end finished but missed the
target), ``stability`` (the coarser end did not finish: the stability boundary, located to the
same 10 %), ``largest setting`` (the coarsest allowed setting meets it: nothing cheaper exists to
find), ``budget`` (the runs ran out first, or a run hit its own step or time budget, after which
the search goes no finer; the row keeps the bracket reached), ``not reached``.

**The answer never extrapolates:** it is the cheapest *measured* setting meeting the target
(for a fixed step, whose error falls with the step, this is the finer end of the final bracket).
An adaptive method's error is not monotone in its tolerance, so the bracket it is bisected to
may be one of several crossings: the same rule (the cheapest measured setting that meets the
target, among every setting the search ran) gives its answer, with its measured neighbours
on either side (``setting_high``: the next coarser measured setting, ``setting_finer``: the next
finer one), and ``non_monotone`` says whether a coarser setting than a failing one met it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

#: Two settings whose costs are within this relative distance are close enough (the issue's 10 %).
RESOLUTION = 0.10
#: The most runs of one search (bracket and bisection together).
MAX_RUNS = 16
#: Statuses of a run stopped by its own budget (steps, seconds): a finer setting costs more, so
#: the search goes no finer after one (its bound is then ``budget``).
BUDGET_STATUSES = ("max_steps", "time_limit")
BOUNDS = ("target", "stability", "largest setting", "budget", "not reached")


@dataclass(frozen=True)
class Point:
    """One run of the search: its setting, status, error (NaN without one) and cost."""

    setting: float
    status: str
    error: float
    cost: float

    @property
    def finished(self) -> bool:
        return self.status == "ok" and math.isfinite(self.error)

    def meets(self, target: float) -> bool:
        return self.finished and self.error <= target


@dataclass
class Found:
    """The outcome of one search (see the module's docstring)."""

    target: float
    bound: str
    setting: float = math.nan  # the answer: the cheapest measured setting meeting the target
    cost: float = math.nan
    error: float = math.nan
    setting_low: float = math.nan  # the bracket's finer end (meets the target): the answer
    setting_high: float = math.nan  # its coarser end (missed, failed, or nan at a range limit)
    setting_finer: float = math.nan  # the measured neighbour finer than the answer, if any
    high_status: str = ""  # the coarser end's status ("ok": it finished and missed the target)
    non_monotone: bool = False
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
    return p.status == "ok" and math.isfinite(p.cost) and p.cost > 0


def close(good: Point, bad: Point, resolution: float = RESOLUTION) -> bool:
    """The bracket (``good`` meets the target, ``bad`` is coarser and does not) is resolved: its
    ends are within ``resolution`` in cost (in setting where ``bad`` has no cost)."""
    if _costed(good) and _costed(bad):
        return good.cost <= bad.cost * (1.0 + resolution)
    return bad.setting <= good.setting * (1.0 + resolution)


def search(run: Callable[[float], tuple[str, float, float]], target: float, start: float, *, lowest: float,
           highest: float, factor: float = 2.0, resolution: float = RESOLUTION, max_runs: int = MAX_RUNS,
           known: dict[float, tuple[str, float, float]] | None = None) -> Found:
    """The cheapest setting in [lowest, highest] at which ``run`` meets ``target`` (module
    docstring). ``known``: results of settings run before (a resumed search), used instead of
    running them again; they count against ``max_runs`` as runs."""
    if not (0 < lowest <= start <= highest) or not all(math.isfinite(v) for v in (lowest, start, highest)):
        raise ValueError(f"search: need 0 < lowest <= start <= highest (got {lowest!r}, {start!r}, {highest!r})")
    if not (factor > 1 and math.isfinite(factor)):
        raise ValueError(f"search: factor = {factor!r} is invalid (allowed: a finite number > 1)")
    if not (target > 0 and math.isfinite(target)):
        raise ValueError(f"search: target = {target!r} is invalid (allowed: a finite number > 0)")
    known = dict(known or {})
    points: dict[float, Point] = {}

    def at(s: float) -> Point:
        s = float(s)
        if s not in points:
            status, error, cost = known[s] if s in known else run(s)
            points[s] = Point(s, str(status), float(error), float(cost))
        return points[s]

    def budget_left() -> bool:
        return len(points) < max_runs

    good = bad = None
    p = at(start)
    if p.meets(target):
        good = p
        while budget_left():  # coarser until missed or failed
            if good.setting >= highest:
                break
            q = at(min(good.setting * factor, highest))
            if q.meets(target):
                good = q
            else:
                bad = q
                break
    else:
        bad = p
        while budget_left():  # finer until met, never past a run stopped by its own budget
            if bad.setting <= lowest or bad.status in BUDGET_STATUSES:
                break
            q = at(max(bad.setting / factor, lowest))
            if q.meets(target):
                good = q
                break
            bad = q
    if good is not None and bad is not None:
        while not close(good, bad, resolution) and budget_left():
            q = at(math.sqrt(good.setting * bad.setting))
            if q.meets(target):
                good = q
            else:
                bad = q
    return _found(list(points.values()), target, lowest, highest, resolution)


def _found(points: list[Point], target: float, lowest: float, highest: float, resolution: float) -> Found:
    ordered = sorted(points, key=lambda p: p.setting)
    meeting = [p for p in ordered if p.meets(target)]
    if not meeting:  # the finest setting allowed missed it too, or the runs (or a run's own budget) ran out
        finest = ordered[0]
        return Found(target, "not reached" if finest.setting <= lowest and finest.status not in BUDGET_STATUSES
                     else "budget",
                     setting_high=ordered[0].setting, high_status=ordered[0].status, points=points)
    # the rule: the cheapest measured setting that meets the target (the coarsest on ties)
    best = min(meeting, key=lambda p: (p.cost if _costed(p) else math.inf, -p.setting))
    i = ordered.index(best)
    coarser = ordered[i + 1] if i + 1 < len(ordered) else None
    finer = ordered[i - 1] if i > 0 else None
    failing_below = [p for p in ordered if p.setting < best.setting and not p.meets(target)]
    out = Found(target, "", setting=best.setting, cost=best.cost, error=best.error, setting_low=best.setting,
                setting_high=coarser.setting if coarser else math.nan,
                setting_finer=finer.setting if finer else math.nan,
                high_status=coarser.status if coarser else "", non_monotone=bool(failing_below), points=points)
    if coarser is None:
        out.bound = "largest setting" if best.setting >= highest else "budget"
    elif coarser.meets(target):  # a coarser setting met it at a higher cost (adaptive)
        out.bound = "target"
    elif not close(best, coarser, resolution):
        out.bound = "budget"
    else:
        out.bound = "target" if coarser.finished else "stability"
    return out

