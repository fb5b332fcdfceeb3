"""Do two runs tables (e.g. the committed ``results/runs.csv`` and a fresh clone's on another CPU)
say the same thing? The reproducibility statement, row by row and in one sentence.

Round-off differs between CPUs (vector widths, fused multiply-add, library kernels), so "the same
to the last digit" holds on one machine only. What holds across machines was measured between
the committed table and a fresh run of the same code on an AMD EPYC (all 147 rows of the default
sweep): every status equal; 13 step counts different (12 adaptive runs by at most 1.25 %, and
one diverged fixed-step run that stopped after 526 instead of 689 steps); 94 energy errors and
128 final position errors different, by a median relative 5e-7. Hence the rules of `AgreementTolerance`:

- **statuses** are equal, except for a fixed-step run *at its method's stability limit* (the
  largest step at which its method finished the scene, or the smallest failing step above it,
  in either table), which may change status;
- **a run that did not finish** in both tables may stop at a different step (where a
  divergence becomes visible follows round-off);
- **fixed-step runs** (``dt`` set) take the same steps and their errors agree to
  ``fixed_error_rtol`` relative plus ``fixed_error_atol`` plus the metric's floor
  (`benchmark.runs.metrics.FLOORS`, below which a value is round-off or the reference's own error):
  measured between the Xeon and the EPYC, no difference above 9e-12 absolute (the reference's own
  round-off), relative differences up to 5e-3 only for values of 5e-10, near the floor. RATTLE
  is the exception, measured later between the committed table (an earlier machine of this
  kind), an Emerald Rapids Xeon (AVX-512) and the same Xeon with XLA held to AVX2
  (``XLA_FLAGS=--xla_cpu_max_isa=AVX2``; tests/data/rattle_*.csv). Its rows differ on each, while
  every other method's default-sweep rows were bit-identical between the first two, and lgvi's
  and lie_rk4's under AVX2 too. Likely cause: its step sums length-N dot products (the
  constraint's normal against the Newton update), whose order XLA's code generation picks per
  CPU, and the pendulum's chaos amplifies that round-off over 10 s. At its finest steps (128,000
  of them) its errors differ by up to 4.2e-10 absolute in energy, 2.6e-10 in π3 (values of
  6e-10, near the floor), and 1.2e-3 relative in attitude and position: far below the 10 % to
  which the answer searches costs;
- **adaptive runs** (``rtol`` set) follow round-off in their step sequence: step counts within
  ``adaptive_steps_rtol``; errors within a factor ``adaptive_error_factor`` of each other, or
  closer than ``adaptive_error_of_rtol`` × the run's rtol (an error far below what its tolerance
  asks is incidental, and its value does not reproduce: measured, DOP853 on deployment at rtol
  1e-4 had energy error 1.9e-8 on one machine and 4.4e-7 on the other, π3 error 1.0e-7 and
  2.7e-6; 90 % of the adaptive errors agreed within a factor 1.11).

Each row's ``used`` is the share of its allowance its largest difference takes (a row differs
when it exceeds 1), so a statement can say how close to its tolerance a comparison came.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from reelbench.benchmark.runs.metrics import ACCURACY, FLOORS
from reelbench.benchmark.core.policy import ROW_IDENTITY, axis_of
from reelbench.integrators.base import FINISHED_STATUSES, is_finished

KEY = list(ROW_IDENTITY)
_REQUIRED = (*KEY, "dt", "rtol", "status", "steps")

#: Verdicts of one row (`compare_runs` decides them, `statement` writes them): equal to the last
#: digit; within `AgreementTolerance`; statuses differ at the method's stability limit; both
#: stopped early, after different step counts; differs; in one table only.
EQUAL, WITHIN_TOLERANCE, AT_STABILITY_LIMIT = "equal", "within tolerance", "at stability limit"
STOPPED_ELSEWHERE, DIFFERS, ONLY_IN_ONE_TABLE = "stopped elsewhere", "differs", "only in one table"
#: Each verdict, and whether it breaks the reproducibility statement.
VERDICTS = {EQUAL: False, WITHIN_TOLERANCE: False, AT_STABILITY_LIMIT: False, STOPPED_ELSEWHERE: False,
            DIFFERS: True, ONLY_IN_ONE_TABLE: True}

COLUMNS = [*KEY, "status_a", "status_b", "steps_a", "steps_b", "metric", "value_a", "value_b", "used", "verdict",
           "reason"]


@dataclass(frozen=True)
class AgreementTolerance:
    """How far two tables of the same sweep (two machines, two passes) may differ and still say the
    same thing: whether two runs agree. Not `benchmark.studies.check.RegressionTolerance`, which decides
    whether a run regressed against the committed baseline. (Defaults from the measured
    Xeon / EPYC and the later RATTLE differences, with margin: see the module's docstring)."""

    #: fixed-step errors: |a − b| <= fixed_error_rtol · max(a, b) + fixed_error_atol + the
    #: metric's floor (measured: RATTLE's finest steps 1.2e-3 relative beyond the absolute term
    #: between CPUs, every other method's 5e-3 only near the floor)
    fixed_error_rtol: float = 1e-2
    #: ... (measured: RATTLE's energy and π3 errors differ by up to 4.2e-10 between CPUs)
    fixed_error_atol: float = 1e-9
    #: adaptive step counts: |a − b| <= adaptive_steps_rtol · max(a, b) (measured: up to 1.25 %)
    adaptive_steps_rtol: float = 0.03
    #: adaptive errors: within this factor of each other (measured: 90 % within 1.11, the largest
    #: factor of a row not also within the rtol rule 1.55) ...
    adaptive_error_factor: float = 2.0
    #: ... or |a − b| <= adaptive_error_of_rtol · rtol (measured: the rows beyond a factor 2 are
    #: within 0.026 · rtol)
    adaptive_error_of_rtol: float = 0.1

    def __post_init__(self):
        for name, lo in (("fixed_error_rtol", 0.0), ("fixed_error_atol", 0.0), ("adaptive_steps_rtol", 0.0),
                         ("adaptive_error_factor", 1.0), ("adaptive_error_of_rtol", 0.0)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= lo and (lo == 0 or v > lo)):
                raise ValueError(f"{type(self).__name__}: {name} = {v!r} is invalid (allowed: a finite number "
                                 f"{'>' if lo else '>='} {lo:g})")


DEFAULT_TOLERANCE = AgreementTolerance()


def _check(table: pd.DataFrame, which: str) -> None:
    missing = [c for c in _REQUIRED if c not in table]
    if missing:
        raise ValueError(f"compare_runs: the {which} table has no column(s) {', '.join(missing)}")
    dup = table.duplicated(KEY)
    if dup.any():
        r = table[dup].iloc[0]
        raise ValueError(f"compare_runs: the {which} table has two rows for {r['scene']}/{r['integrator']}/{r['setting']}")


def stability_limits(table: pd.DataFrame) -> set[tuple[str, str, float]]:
    """(scene, integrator, dt) of the fixed-step runs at their method's stability limit in one
    runs table: the largest step at which the method finished the scene, and the smallest step
    above it at which it failed."""
    out = set()
    for (scene, integ), g in table[table["dt"].notna()].groupby(["scene", "integrator"]):
        ok = g.loc[g["status"].isin(FINISHED_STATUSES), "dt"]
        if ok.empty:
            continue
        out.add((scene, integ, float(ok.max())))
        above = g.loc[~g["status"].isin(FINISHED_STATUSES) & (g["dt"] > ok.max()), "dt"]
        if len(above):
            out.add((scene, integ, float(above.min())))
    return out


def error_share(a: float, b: float, floor: float, rtol: float | None, tol: AgreementTolerance) -> float:
    """The share of its allowance the difference of two values of one metric takes (<= 1: within
    tolerance); ``rtol`` None for a fixed-step run, else the adaptive run's tolerance."""
    if a == b or (np.isnan(a) and np.isnan(b)):
        return 0.0
    if np.isnan(a) or np.isnan(b):
        return math.inf
    diff = abs(a - b)
    if rtol is None:
        allowance = tol.fixed_error_rtol * max(abs(a), abs(b)) + tol.fixed_error_atol + floor
        return diff / allowance if allowance > 0 else math.inf
    lo, hi = sorted((max(abs(a), floor), max(abs(b), floor)))
    by_factor = math.log(hi / lo) / math.log(tol.adaptive_error_factor)
    by_rtol = diff / (tol.adaptive_error_of_rtol * rtol) if tol.adaptive_error_of_rtol > 0 else math.inf
    return min(by_factor, by_rtol)


def compare_runs(a: pd.DataFrame, b: pd.DataFrame, tol: AgreementTolerance = DEFAULT_TOLERANCE,
                 metrics: tuple[str, ...] | None = None) -> pd.DataFrame:
    """One row per (scene, integrator, setting) of either table: both statuses and step counts,
    the quantity that uses most of its allowance (``metric``: an error column or "steps") with
    both values and the share ``used``, and the verdict (a key of `VERDICTS`) with its reason.
    ``metrics``: the error columns compared (default: the `ACCURACY` metrics both tables have)."""
    _check(a, "first")
    _check(b, "second")
    metrics = tuple(m for m in (metrics or ACCURACY) if m in a and m in b)
    limits = stability_limits(a) | stability_limits(b)
    both = a.merge(b, on=KEY, how="outer", suffixes=("_a", "_b"), indicator=True)
    rows = []
    for r in both.to_dict("records"):
        out = {k: r[k] for k in KEY}
        out.update(status_a=r["status_a"], status_b=r["status_b"], steps_a=r["steps_a"], steps_b=r["steps_b"],
                   metric="", value_a=np.nan, value_b=np.nan, used=np.nan, reason="")
        dt = r["dt_a"] if pd.notna(r["dt_a"]) else r["dt_b"]
        if r["_merge"] != "both":
            out.update(verdict=ONLY_IN_ONE_TABLE,
                       reason=f"only in the {'first' if r['_merge'] == 'left_only' else 'second'} table")
        elif r["status_a"] != r["status_b"]:
            at_limit = pd.notna(dt) and (r["scene"], r["integrator"], float(dt)) in limits
            out.update(verdict=AT_STABILITY_LIMIT if at_limit else DIFFERS,
                       reason=f"status {r['status_a']} vs {r['status_b']}"
                              + (" at the method's stability limit" if at_limit else ""))
        elif not is_finished(r["status_a"]):
            same = r["steps_a"] == r["steps_b"]
            out.update(verdict=EQUAL if same else STOPPED_ELSEWHERE,
                       reason="" if same else f"both {r['status_a']}, after {r['steps_a']:.0f} vs {r['steps_b']:.0f} steps")
        else:
            out.update(_compare_finished(r, metrics, None if pd.notna(dt) else float(r["rtol_a"]), tol))
        rows.append(out)
    return pd.DataFrame(rows, columns=COLUMNS)


def _compare_finished(r: dict, metrics, rtol: float | None, tol: AgreementTolerance) -> dict:
    """Verdict of a run both tables finished; ``rtol`` None for a fixed-step run."""
    sa, sb = r["steps_a"], r["steps_b"]
    if rtol is None:
        steps_used = 0.0 if sa == sb else math.inf
    else:
        steps_used = abs(sa - sb) / (tol.adaptive_steps_rtol * max(sa, sb, 1)) if tol.adaptive_steps_rtol else (
            0.0 if sa == sb else math.inf)
    shares = {"steps": (steps_used, sa, sb)}
    for m in metrics:
        va, vb = float(r[f"{m}_a"]), float(r[f"{m}_b"])
        shares[m] = (error_share(va, vb, FLOORS.get(m, 0.0), rtol, tol), va, vb)
    worst = max(shares, key=lambda k: shares[k][0])
    used, va, vb = shares[worst]
    exact = all(s[1] == s[2] or (np.isnan(s[1]) and np.isnan(s[2])) for s in shares.values())
    verdict = EQUAL if exact else (WITHIN_TOLERANCE if used <= 1 else DIFFERS)
    fmt = ".0f" if worst == "steps" else ".3g"
    return {"verdict": verdict, "metric": "" if exact else worst, "value_a": va, "value_b": vb, "used": used,
            "reason": "" if exact else f"{worst} {va:{fmt}} vs {vb:{fmt}} ({used:.2g} of its allowance)"}


def reproducible(comparison: pd.DataFrame) -> bool:
    """Whether a `compare_runs` table upholds the statement (no row ``differs`` or is missing)."""
    return not comparison["verdict"].map(VERDICTS).any()


def statement(comparison: pd.DataFrame, tol: AgreementTolerance = DEFAULT_TOLERANCE) -> str:
    """The reproducibility statement for a README, from a `compare_runs` table: how many runs
    were equal to the last digit, how many within tolerance and how close to it they came, the
    documented exceptions, and every row that breaks it."""
    c = comparison
    n = c["verdict"].value_counts()
    fixed = c["setting"].map(axis_of) == "dt"
    within = c["verdict"] == WITHIN_TOLERANCE
    text = (f"{len(c)} runs compared: {n.get(EQUAL, 0)} equal to the last digit, "
            f"{n.get(WITHIN_TOLERANCE, 0)} {WITHIN_TOLERANCE} (fixed-step: same steps, errors within "
            f"{tol.fixed_error_rtol:g} relative plus {tol.fixed_error_atol:g} and the metric's floor; "
            f"adaptive: steps within {tol.adaptive_steps_rtol:.0%}, "
            f"errors within a factor {tol.adaptive_error_factor:g} or "
            f"{tol.adaptive_error_of_rtol:g} × rtol)")
    shares = [f"{what} {c.loc[within & sel, 'used'].max():.2g}" for what, sel in (("fixed-step", fixed),
                                                                                  ("adaptive", ~fixed))
              if (within & sel).any()]
    if shares:
        text += "; largest share of the allowance used: " + ", ".join(shares)
    for v in (AT_STABILITY_LIMIT, STOPPED_ELSEWHERE):
        g = c[c["verdict"] == v]
        if len(g):
            text += f"; {len(g)} {v}: " + ", ".join(f"`{r.integrator}` {r.setting} on {r.scene} ({r.reason})"
                                                   for r in g.itertuples())
    bad = c[c["verdict"].map(VERDICTS)]
    text += "; every other claim holds." if bad.empty else f"; {len(bad)} differ: " + ", ".join(
        f"`{r.integrator}` {r.setting} on {r.scene} ({r.reason})" for r in bad.itertuples()) + "."
    return text
