"""`python -m benchmark orders`: observed orders on a short horizon (`benchmark.studies.orders`),
on the one study runner (`benchmark.core.study.run`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar


def cmd_orders(args) -> int:
    from reelbench.benchmark.studies import orders
    from reelbench.models import load_scene

    for sc in args.scenes or ():
        load_scene(sc)  # an unknown scene is refused before any work
    the_study = orders.study(args.scenes, args.integrators, workers=args.jobs,  # an adaptive-only method likewise
                             budget=common.budget(args))
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, ("orders_errors.csv", "orders.csv"))
    from reelbench.benchmark.core import study

    return study.run(the_study, out, command=common.command(args), fresh=args.fresh, log=_log)


def add_orders(sub) -> None:
    from reelbench.benchmark.studies import orders  # constants only (no JAX)

    o = sub("orders", "observed orders of the fixed-step methods on a short horizon, against a reference "
                      "100x more accurate -> OUT/orders.csv",
            f"Each fixed-step method at {orders.HALVINGS} halvings of its step on a {orders.T_END:g} s horizon of "
            f"each scene (N = {orders.ELEMENTS}), against constant-step {orders.REFERENCE_METHOD}; the order is the "
            "slope of the last halving above the reference's floor, flagged when not asymptotic (see "
            "benchmark/studies/orders.py). Rows of other scenes and methods in OUT/orders.csv are kept.")
    common.add_scenes(o, f"(default: {common.csv_of(orders.SCENES)}, one per situation)")
    common.add_integrators(o, "fixed-step methods only (default: every registered one)", registered=False)
    common.add_jobs(o, common.DEFAULT_JOBS.format(unit="method"))
    common.add_budget(o, "the ladder goes on (its row says so)")
    common.add_fresh(o, "OUT/orders_errors.csv")
    common.add_out(o, "output directory (created if missing)", default=str(policy.RESULTS))
    o.set_defaults(func=cmd_orders)
