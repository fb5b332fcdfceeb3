"""`python -m benchmark reel-reversal`: orders across a reel reversal
(`benchmark.studies.reel_reversal`), on the one study runner (`benchmark.core.study.run`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError


def cmd_reel_reversal(args) -> int:
    from reelbench.benchmark.studies import reel_reversal
    from reelbench.models import load_scene

    reel_reversal.check_methods(args.integrators or ())
    reel_reversal.check_horizon(args.t_end)
    scene = load_scene(args.scene, elements=args.elements)
    if not scene.has("reel"):  # its "error" column would be a node coordinate, its sign changes noise
        raise UsageError(f"--scenes {scene.name!r} has no reel (effects: {', '.join(scene.effects)}): the reel-reversal "
                         "study follows the reel rate through its change of sign; give a scene with the reel effect, "
                         "e.g. --scenes reel_reversal")
    from reelbench.benchmark.core import study
    from reelbench.benchmark.core.reference import CACHE_DIR

    cache = opt.writable_dir(args.cache_dir or CACHE_DIR, option="--cache-dir")
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, ("reel_reversal.csv", "reel_reversal.md"))
    the_study = reel_reversal.study(args.scene, args.elements, args.t_end, args.integrators, workers=args.jobs,
                                    cache_dir=str(cache), budget=common.budget(args))
    return study.run(the_study, out, command=common.command(args), fresh=args.fresh, log=_log)


def add_reel_reversal(sub) -> None:
    from reelbench.benchmark.studies import reel_reversal  # constants only (no JAX)

    rr = sub("reel-reversal", "orders of the fixed-step methods across a reel reversal (ṡ_p changes sign), errors "
                              "against the reference -> --out/reel_reversal.csv, reel_reversal.md (also printed)")
    common.add_scenes(rr, "a scene with the reel effect", one=True, default="reel_reversal")
    common.add_elements(rr, "", one=True, default=5)
    common.add_t_end(rr, f"a multiple of the compared interval {reel_reversal.COMPARE_EVERY:g} s", default=0.96)
    common.add_integrators(rr, f"fixed-step methods with a step list (default: {common.csv_of(reel_reversal.DEFAULT_HS)})",
                           registered=False)
    common.add_jobs(rr, common.DEFAULT_JOBS.format(unit="method"))
    common.add_budget(rr, "the study goes on (such a row is recomputed on resume)")
    rr.add_argument("--cache-dir", help="where the reference is cached (default: the user's cache, shared by every "
                                        "study; created if missing)")
    common.add_fresh(rr, "OUT/reel_reversal.csv")
    common.add_out(rr, "output directory (created if missing); rows of other cases, methods and steps are kept",
                   default=str(reel_reversal.OUT_DIR))
    rr.set_defaults(func=cmd_reel_reversal)
