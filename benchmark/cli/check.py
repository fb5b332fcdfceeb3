"""`python -m benchmark check`: the drift check against the committed baseline (rules in
`benchmark.studies.check`), its options checked, then `benchmark.studies.check.run_check`.
"""

from __future__ import annotations

import shlex
from pathlib import Path

from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError


def cmd_check(args) -> int:
    from reelbench.benchmark.studies import check

    if not args.update and args.baseline is None and not Path(check.BASELINE).exists():
        raise UsageError(f"the committed baseline {check.BASELINE} is not in {Path.cwd()}: run `check` from the "
                         f"repository's root directory, or give --baseline PATH")
    # how the baseline was produced, for its header (the options that change its content)
    command = check.UPDATE_COMMAND + "".join(f" --{k} {shlex.quote(v)}" for k, v in
                                             (("integrators", ",".join(args.integrators or ())),
                                              ("baseline", args.baseline)) if v)
    # --integrators and --allow-new: registered names, --factor and --order-margin in range (parsed)
    return check.run_check(update=args.update, baseline=args.baseline, integrators=args.integrators,
                           factor=args.factor, order_margin=args.order_margin, jobs=args.jobs, command=command,
                           allow_new=tuple(args.allow_new or ()), budget=common.budget(args), log=_log)


def add_check(sub) -> None:
    c = sub("check", "recompute a short sweep and compare its accuracy metrics with the committed baseline; "
                     "exit 1 on a regression (rules in benchmark/studies/check.py)")
    c.add_argument("--update", action="store_true", help="rewrite the baseline from this run instead of failing")
    common.add_budget(c, "the check goes on")
    c.add_argument("--baseline", help=f"baseline CSV (default: {policy.BASELINE_FILE}, run from the repository root)")
    common.add_integrators(c, "(default: all registered except test_*)")
    c.add_argument("--factor", type=common.ruled(opt.number, opt.check_factor, "factor"),
                   help=f"a drift or error fails when worse than FACTOR x baseline, above its floor (default: "
                        f"{policy.CHECK_FACTOR:g})")
    c.add_argument("--order-margin", type=common.ruled(opt.number, opt.check_order_margin, "margin"),
                   help="an observed order fails when lower than baseline - MARGIN (default: "
                        f"{policy.CHECK_ORDER_MARGIN:g})")
    common.add_jobs(c, "the CPU count", workers_only="check runs its sweep in worker processes")
    c.add_argument("--allow-new", type=common.integrator_names, metavar="NAMES",
                   help="comma-separated integrators that may lack baseline rows (new methods); any other selected "
                        "integrator without rows to compare fails the check (exit 2)")
    common.add_check(c, _allow_new_checks_against_the_baseline)
    c.set_defaults(func=cmd_check)


def _allow_new_checks_against_the_baseline(args) -> None:
    if args.allow_new and args.update:
        raise UsageError("--allow-new is for a check against the baseline; --update writes the rows of every "
                         "integrator it runs")
