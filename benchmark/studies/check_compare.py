"""The comparison of `python -m benchmark check` (`benchmark.studies.check`): a check table
against its baseline under the regression rules (`RegressionTolerance`, the rules of the check's
docstring), and the readable report of the outcome.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from reelbench.benchmark.core.options import check_tolerance_rules
from reelbench.benchmark.core.policy import CHECK_FACTOR, CHECK_ORDER_MARGIN
from reelbench.benchmark.core.report import fmt, markdown_table, one_minute_load
from reelbench.benchmark.runs.metrics import ACCURACY, DIRECTIONS
from reelbench.benchmark.studies.check_baseline import FLOORS, KEY, ORDER, UPDATE_COMMAND, is_order_row, name_of
from reelbench.integrators import available, plugin_errors
from reelbench.integrators.base import Status, is_finished

DEFAULT_FACTOR, DEFAULT_ORDER_MARGIN = CHECK_FACTOR, CHECK_ORDER_MARGIN
#: The status a run of a usable baseline has: the finished one.
OK = Status.OK.value


@dataclass(frozen=True)
class RegressionTolerance:
    """What the drift gate calls a regression of a run against its baseline (the rules of
    `benchmark.studies.check`'s docstring): a metric worse than ``factor`` × baseline above its floor, an order lower by more
    than ``order_margin``. Not `benchmark.runs.reproducibility.AgreementTolerance`, which decides
    whether two runs of the same sweep on two machines agree."""

    factor: float = DEFAULT_FACTOR
    order_margin: float = DEFAULT_ORDER_MARGIN
    floors: dict = field(default_factory=lambda: dict(FLOORS))

    def __post_init__(self):
        check_tolerance_rules(self.factor, self.order_margin)


@dataclass
class Comparison:
    """The outcome of `compare`: regressions (the check fails on any), improvements, notes and
    the timing table (informational), and how many rows were compared and bit-identical."""

    regressions: list[dict] = field(default_factory=list)  # scene, integrator, setting, metric, baseline, current, change, allowed
    improvements: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    timing: pd.DataFrame = field(default_factory=pd.DataFrame)
    compared: int = 0
    identical: int = 0  # rows whose status and metrics equal the baseline's bit for bit

    @property
    def failed(self) -> bool:
        return bool(self.regressions)

    def regression(self, key, metric, b, c, change, allowed) -> None:
        self.regressions.append(dict(zip(KEY, key), metric=metric, baseline=b, current=c, change=change, allowed=allowed))

    def improvement(self, key, metric, b, c, change) -> None:
        self.improvements.append(dict(zip(KEY, key), metric=metric, baseline=b, current=c, change=change, allowed=""))


def _g(v: float) -> str:
    return fmt(v, missing="nan")


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))


def compare(baseline: pd.DataFrame, current: pd.DataFrame, tol: RegressionTolerance = RegressionTolerance(), *,
            registered: list[str] | None = None, load_errors: dict[str, str] | None = None) -> Comparison:
    """Compare ``current`` with ``baseline`` (both in the layout of `benchmark.studies.check.to_table`) under ``tol``.
    ``registered`` / ``load_errors`` default to the registry's `available()` / `plugin_errors()`."""
    registered = set(available() if registered is None else registered)
    load_errors = plugin_errors() if load_errors is None else load_errors
    out = Comparison()
    base = baseline.set_index(KEY)
    cur = current.set_index(KEY)
    _compare_membership(out, base, cur, registered, load_errors)
    for key in cur.index.intersection(base.index, sort=False):
        b, c = base.loc[key], cur.loc[key]
        out.compared += 1
        out.identical += all(_same(b[m], c[m]) for m in ["status", *ACCURACY, ORDER])
        if is_order_row(key[2]):
            _compare_order(out, key, float(b[ORDER]), float(c[ORDER]), tol)
        elif _compare_status(out, key, b, c):
            _compare_metrics(out, key, b, c, tol)
    out.timing = _timing(base, cur)
    return out


def _compare_membership(out: Comparison, base: pd.DataFrame, cur: pd.DataFrame, registered: set,
                        load_errors: dict) -> None:
    """Integrators and rows on one side only: notes, except a baseline integrator whose module
    stopped loading (a regression: it must not drop out of the check silently)."""
    ran = set(cur.index.get_level_values("integrator"))
    based = set(base.index.get_level_values("integrator"))
    for name in sorted(ran - based):
        out.notes.append(f"{name}: no baseline, run `{UPDATE_COMMAND}`")
    for name in sorted(based - registered):
        if name in load_errors:
            out.regression(("*", name, "*"), "load", "registered", f"failed to load: {load_errors[name]}"[:80], "gone",
                           "loads")
        else:  # removed or renamed: its rows would drop out of the check silently
            out.regression(("*", name, "*"), "registered", "registered", "not registered (removed or renamed?)",
                           "gone", "registered")
    for key in cur.index.difference(base.index):
        if key[1] in based:
            out.notes.append(f"{name_of(key)}: new in the sweep, no baseline row (run `{UPDATE_COMMAND}`)")
    for key in base.index.difference(cur.index):
        if key[1] in ran:
            out.notes.append(f"{name_of(key)}: in the baseline but not in this sweep")


def _compare_order(out: Comparison, key, bo: float, co: float, tol: RegressionTolerance) -> None:
    if np.isfinite(bo) and np.isfinite(co):
        if co < bo - tol.order_margin:
            out.regression(key, ORDER, _g(bo), _g(co), f"{co - bo:+.2f}", f">= {bo - tol.order_margin:.3g}")
        elif co > bo + tol.order_margin:
            out.improvement(key, ORDER, _g(bo), _g(co), f"{co - bo:+.2f}")
    elif np.isfinite(bo) != np.isfinite(co):
        # fewer than two usable points: a failed run (reported by its status) or errors
        # now below the floor (an improvement); nothing to compare
        out.notes.append(f"{name_of(key)}: {ORDER} {_g(bo)} -> {_g(co)} (not comparable)")


def _compare_status(out: Comparison, key, b: pd.Series, c: pd.Series) -> bool:
    """ok -> not ok is a regression, the reverse an improvement; True when both runs are ok
    (then their metrics are compared)."""
    bs, cs = b["status"], c["status"]
    if bs != cs:
        text = f"{cs}: {c['reason']}"[:80] if not is_finished(cs) else cs
        if is_finished(bs):
            out.regression(key, "status", bs, text, f"no longer {OK}", OK)
        elif is_finished(cs):
            out.improvement(key, "status", bs, cs, f"now {OK}")
        else:
            out.notes.append(f"{name_of(key)}: status {bs} -> {text}")
    return is_finished(bs) and is_finished(cs)


def _compare_metrics(out: Comparison, key, b: pd.Series, c: pd.Series, tol: RegressionTolerance) -> None:
    for m in ACCURACY:
        bv, cv = float(b[m]), float(c[m])
        if not np.isfinite(bv):
            if np.isfinite(cv):  # nothing to compare with is a failure, not a pass
                out.regression(key, m, _g(bv), _g(cv), "missing in the baseline", "a finite baseline value")
            continue
        floor = tol.floors.get(m, 0.0)
        if DIRECTIONS.get(m, "lower") == "lower":  # smaller is better: worse is above factor x baseline
            limit = max(tol.factor * bv, floor)
            if not np.isfinite(cv) or cv > limit:
                change = f"x{cv / bv:.3g}" if np.isfinite(cv) and bv > 0 else "missing" if not np.isfinite(cv) else "from 0"
                out.regression(key, m, _g(bv), _g(cv), change, f"<= {_g(limit)}")
            elif bv > floor and cv < bv / tol.factor:
                out.improvement(key, m, _g(bv), _g(cv), f"x{cv / bv:.3g}")
        else:  # larger is better: worse is below baseline / factor (values under the floor never fail)
            limit = bv / tol.factor
            if not np.isfinite(cv) or (cv < limit and bv > floor):
                change = f"x{cv / bv:.3g}" if np.isfinite(cv) and bv > 0 else "missing"
                out.regression(key, m, _g(bv), _g(cv), change, f">= {_g(limit)}")
            elif cv > tol.factor * bv and cv > floor:
                out.improvement(key, m, _g(bv), _g(cv), f"x{cv / bv:.3g}")


def _timing(base: pd.DataFrame, cur: pd.DataFrame) -> pd.DataFrame:
    """Run and compile time per integrator, summed over the runs present in both (informational)."""
    both = cur.index.intersection(base.index, sort=False)
    both = [k for k in both if not is_order_row(k[2])]
    if not both:
        return pd.DataFrame()
    rows = []
    b, c = base.loc[both], cur.loc[both]
    for name in sorted({k[1] for k in both}):
        sb, sc = b.xs(name, level="integrator"), c.xs(name, level="integrator")
        rb, rc = float(np.nansum(sb["run_time"])), float(np.nansum(sc["run_time"]))
        row = {"integrator": name, "runs": len(sc), "run_time_baseline": rb, "run_time": rc,
               "ratio": rc / rb if rb > 0 else np.nan,
               "compile_time_baseline": float(np.nansum(sb["compile_time"])),
               "compile_time": float(np.nansum(sc["compile_time"]))}
        # the load average each side's runs were timed under (when recorded): a ratio far from 1
        # under a different load is the machine's, not the method's
        for col, side in (("load_baseline", sb), ("load", sc)):
            if "load_avg" in side:
                loads = pd.to_numeric(side["load_avg"], errors="coerce")
                row[col] = float(loads.mean()) if loads.notna().any() else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def machine_load() -> str:
    """"load average L over C cores" of this machine now (empty where the OS does not say)."""
    load = one_minute_load()
    return f"load average {load:.1f} over {os.cpu_count()} cores" if load == load else ""


def format_report(cmp: Comparison, tol: RegressionTolerance, baseline_path,
                  baseline_header: list[str] | None = None) -> str:
    """The readable outcome: regressions, improvements, notes, timing, verdict."""
    # "Produced by": the header of baselines written before the shared report header
    made = next((h for h in baseline_header or [] if h.startswith(("Generated by", "Produced by"))), "")
    lo, hi = min(tol.floors.values()), max(tol.floors.values())
    floors = f"{lo:.0e}" if lo == hi else ", ".join(f"{k} {v:.0e}" for k, v in tol.floors.items())
    load = machine_load()
    out = [f"check: {cmp.compared} rows compared with {baseline_path}, {cmp.identical} bit-identical"
           + (f" ({made})" if made else ""),
           f"rules: drifts/errors fail above x{tol.factor:g} the baseline and above their floor ({floors}); "
           "observed orders fail below "
           f"baseline - {tol.order_margin:g}; ok -> not ok fails; timing never fails.",
           "informational (never a failure): the bit-identical count (another CPU or XLA build changes the last "
           "digits, so 0 is normal there: the rules above decide), the notes and the timing table"
           + (f"; this machine now: {load}" if load else "") + ".", ""]
    cols = KEY + ["metric", "baseline", "current", "change", "allowed"]
    if cmp.regressions:
        out += [f"## REGRESSIONS ({len(cmp.regressions)})", "", markdown_table(pd.DataFrame(cmp.regressions, columns=cols))]
    if cmp.improvements:
        out += [f"## improvements ({len(cmp.improvements)}): refresh the baseline with `{UPDATE_COMMAND}` to keep them",
                "", markdown_table(pd.DataFrame(cmp.improvements, columns=cols[:-1]))]
    if cmp.notes:
        out += [f"## notes ({len(cmp.notes)}, not failures)", ""] + [f"- {n}" for n in cmp.notes] + [""]
    if not cmp.timing.empty:
        out += ["## timing (s, first solve after compilation; informational, never fails)", "",
                "Run times scale with the machine and its load (load: the mean load average the runs were "
                "timed under, where recorded" + (f"; {load} now" if load else "") + "): a ratio far from 1 "
                "under another load or on another machine is not a regression.", "",
                markdown_table(cmp.timing)]
    out.append(f"check FAILED: {len(cmp.regressions)} regression(s)" if cmp.failed else
               f"check passed: no regressions ({len(cmp.improvements)} improvement(s), {len(cmp.notes)} note(s))")
    return "\n".join(out)
