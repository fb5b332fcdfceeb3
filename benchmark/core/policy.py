"""The benchmark's rules, each stated once: how a run is saved and toleranced, what one solve may
spend, how finely an answer is resolved and the words of its verdicts, which reference each
study compares with, and where results go. Every study reads them from here; nothing here
imports JAX (the command line checks its input against them in milliseconds).

Rules of one integrator call (the number of fixed steps, the saved memory, the planned-step cap,
the horizon, the step mode) are the integrators' own: `integrators.base` and
`integrators.lifecycle`, which the command line calls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

# ------------------------------------------------------------------------------------------
# A run's save interval and tolerances
# ------------------------------------------------------------------------------------------
#: s; the save times of every run of the sweep and the answer (a fixed step saves at its step
#: points nearest them), and `simulate`'s default.
SAVE_EVERY = 0.02
#: atol = rtol × ATOL_FACTOR wherever a study or the command line gives a tolerance alone.
ATOL_FACTOR = 1e-2


def atol_for(rtol: float) -> float:
    """The absolute tolerance that goes with ``rtol`` (`ATOL_FACTOR`)."""
    return rtol * ATOL_FACTOR


@dataclass(frozen=True)
class Setting:
    """One run's setting: a fixed step ``dt``, or a tolerance ``rtol`` with its ``atol``.

    It carries its label ("dt=0.005", "rtol=1e-06": the runs table's ``setting`` column) and the
    solve keyword arguments it stands for, so that no study formats or parses either by hand."""

    dt: float | None = None
    rtol: float | None = None
    atol: float | None = None

    def __post_init__(self):
        if (self.dt is None) == (self.rtol is None):
            raise ValueError(f"a setting is a step dt or a tolerance rtol, one of them (got dt = {self.dt!r}, "
                             f"rtol = {self.rtol!r})")

    @classmethod
    def fixed(cls, dt: float) -> "Setting":
        return cls(dt=float(dt))

    @classmethod
    def adaptive(cls, rtol: float, atol: float | None = None) -> "Setting":
        """``rtol`` with ``atol`` (default: `atol_for`)."""
        return cls(rtol=float(rtol), atol=atol_for(float(rtol)) if atol is None else atol)

    @classmethod
    def on_axis(cls, axis: str, value: float) -> "Setting":
        """The setting ``value`` on a sweep axis ("dt" or "rtol")."""
        if axis == "dt":
            return cls.fixed(value)
        if axis == "rtol":
            return cls.adaptive(value)
        raise ValueError(f"axis = {axis!r} is invalid (allowed: dt, rtol)")

    @classmethod
    def parse(cls, label: str) -> "Setting":
        """The setting a label names ("dt=0.005", "rtol=1e-06", "rtol=1e-06, atol=1e-08");
        ValueError for any other text."""
        axis, value = axis_value(label)
        if axis == "rtol" and "atol=" in str(label):
            return cls.adaptive(value, float(str(label).split("atol=")[1]))
        return cls.on_axis(axis, value)

    @property
    def axis(self) -> str:
        """The sweep axis: "dt" (a fixed step) or "rtol" (adaptive)."""
        return "dt" if self.dt is not None else "rtol"

    @property
    def value(self) -> float:
        """The step or the tolerance (larger: coarser)."""
        return self.dt if self.dt is not None else self.rtol

    def label(self, digits: int = 6) -> str:
        """"dt=0.005" / "rtol=1e-06": the axis and the value to ``digits`` significant digits."""
        return f"{self.axis}={self.value:.{digits}g}"

    def solve_kwargs(self) -> dict:
        """The keyword arguments of `Integrator.solve` this setting stands for."""
        return {"dt": self.dt} if self.dt is not None else {"rtol": self.rtol, "atol": self.atol}


def axis_value(label: str) -> tuple[str, float]:
    """(axis, value) of a setting's label ("dt=0.005" -> ("dt", 0.005); "rtol=1e-06, atol=1e-08" ->
    ("rtol", 1e-06)); ValueError for text that is not one."""
    head = str(label).split(",")[0]
    axis, sep, value = head.partition("=")
    if not sep or axis.strip() not in ("dt", "rtol"):
        raise ValueError(f"{label!r} is not a setting (allowed: dt=..., rtol=...)")
    return axis.strip(), float(value)


def axis_of(label) -> str | None:
    """"dt" or "rtol" for a setting's label, None for any other text."""
    try:
        return axis_value(label)[0]
    except ValueError:
        return None


def setting_value(label, missing: float = math.nan) -> float:
    """The step or tolerance a setting's label names (larger: coarser), ``missing`` for other text."""
    try:
        return axis_value(label)[1]
    except ValueError:
        return missing


#: A run's place in a runs table (and in the drift gate's baseline and a reproducibility
#: comparison): one row per scene, integrator and setting label.
ROW_IDENTITY = ("scene", "integrator", "setting")


# ------------------------------------------------------------------------------------------
# What one solve may spend
# ------------------------------------------------------------------------------------------
#: Every study solve's default budgets (raised by --max-steps / --time-limit on every command that
#: solves; the answer's searches have their own, below): a request that would run for hours (a tolerance near round-off over a
#: long horizon) ends with status max_steps / time_limit (`simulate` saves its trajectory), and a
#: sweep goes on with its other runs.
SOLVE_MAX_STEPS = 10_000_000
SOLVE_TIME_LIMIT = 1800.0
#: The answer's searches: one solve's run time (s), and no step cap (a run past it is
#: ``time_limit``: not finished, finer settings cost more).
SEARCH_TIME_LIMIT = 60.0
#: Seconds of paired timing per target of the answer (all methods' solves together, the setup
#: excluded: `benchmark.answer.paired`).
PAIRED_BUDGET = 20.0

# ------------------------------------------------------------------------------------------
# How finely an answer is resolved
# ------------------------------------------------------------------------------------------
#: The issue's 10 %: two settings whose costs are within it are close enough (the search's
#: bracket, the work verdicts), and a paired timing stops once every ratio's interval lies within
#: it of the ratio.
RESOLUTION = 0.10
#: Wall-time ratios this close to 1 are a tie whatever their interval: measured, not chosen (the
#: largest change of a ratio between two quiet timing passes of the 12 committed targets was
#: 10.7 %; `benchmark.answer.paired`). Equal to `RESOLUTION` by measurement, not by definition.
TIE_MARGIN = 0.10

#: The drift gate's defaults (`benchmark check`, `check.RegressionTolerance`): a metric fails when
#: worse than CHECK_FACTOR × its baseline above its floor (×2 lets a refactoring's reordered
#: floating-point work through, a real regression moves by orders of magnitude), an observed order
#: when lower than its baseline by more than CHECK_ORDER_MARGIN.
CHECK_FACTOR = 2.0
CHECK_ORDER_MARGIN = 0.5

# ------------------------------------------------------------------------------------------
# The words of the answer's verdicts (cheapest.csv's ``verdict``)
# ------------------------------------------------------------------------------------------
#: A ranking's verdicts, by wall time (`benchmark.answer.paired.verdicts`) and by work
#: (`benchmark.runs.ranking.work_verdicts`): the cheapest alone; the cheapest, and each method
#: whose interval it cannot be told from; every other method.
WINNER, TIE, SLOWER = "winner", "tie", "slower"
RANKED_VERDICTS = (WINNER, TIE, SLOWER)
#: The ranked verdicts of the methods the answer recommends.
BEST_VERDICTS = (WINNER, TIE)
#: The work verdicts of a method the answer does not rank (`benchmark.answer.table.answer_table`):
#: its search is bit-identical to another method's (ranked as one entry); its cost is not in
#: flops; its flops are only a lower bound, below the winner's; it reached no setting at the
#: target (also the search's ``bound``, `benchmark.answer.search`).
IDENTICAL, NO_FLOPS_COUNT, LOWER_BOUND, NOT_REACHED = "identical", "no flops count", "lower bound", "not reached"
UNRANKED_VERDICTS = (IDENTICAL, NO_FLOPS_COUNT, LOWER_BOUND, NOT_REACHED)

# ------------------------------------------------------------------------------------------
# References: what each study compares with (they differ where their purpose does)
# ------------------------------------------------------------------------------------------
#: The runs table's and the answer's reference (`benchmark.core.reference`, cached per problem): scipy's
#: DOP853 on the closed-form right-hand side, 1e-12 / 1e-14, two decades tighter than the
#: tightest tolerance a study sweeps (1e-10) and 1e-13 below the search's finest.
REFERENCE_METHOD = {"integrator": "dop853", "rtol": 1e-12, "atol": 1e-14}
#: The order ladders' reference (`benchmark.studies.orders`): an error bound is needed, not just a small
#: error, so a constant-step eighth-order run at this step, bounded against twice that step ...
ORDERS_REFERENCE_METHOD, ORDERS_REFERENCE_DT = "dopri8", 0.000625
#: ... and checked independently by another eighth-order tableau, at tolerances tighter than the
#: shared reference's (the ladders' errors go down to 1e-12).
ORDERS_CHECK_METHOD = {"integrator": "dop853", "rtol": 1e-13, "atol": 1e-15}
#: `benchmark.contract.verify`'s tiny-scene reference, scipy's solve_ivp called directly on three elements
#: (no cache, no adapter: the check of the adapters must not rest on one of them).
VERIFY_REFERENCE = {"method": "DOP853", "rtol": 1e-13, "atol": 1e-14}
#: `benchmark.contract.verify`'s energy-balance check of a dissipative effect over its longer horizon: only
#: the balance's order of magnitude is judged, so a looser, cheaper solve serves.
VERIFY_BALANCE_REFERENCE = {"method": "DOP853", "rtol": 1e-11, "atol": 1e-12}

# ------------------------------------------------------------------------------------------
# Where results go (relative to the working directory, as the commands take them)
# ------------------------------------------------------------------------------------------
RESULTS = Path("results")
#: `run`'s committed grid sweep.
GRID_DIR = RESULTS / "grid"
#: `check`'s baseline of the drift gate.
BASELINE_FILE = RESULTS / "baseline" / "drift.csv"
#: The answer's table (`answer` writes it into its --out, results/ by default).
CHEAPEST_FILE = RESULTS / "cheapest.csv"
STABILITY_DIR = RESULTS / "stability"
XVAL_DIR = RESULTS / "xval"
LGVI_SPEED_FILE = RESULTS / "lgvi_speed.md"
WORK_RULE_FILE = RESULTS / "work_rule.md"

