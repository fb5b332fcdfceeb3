"""`python -m benchmark stability`: the stability map of the hard scenes
(`benchmark.studies.stability`), on the one study runner (`benchmark.core.study.run`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar


def cmd_stability(args) -> int:
    from reelbench.benchmark.core import study
    from reelbench.benchmark.studies import stability

    # the study checks its scene and integrator names
    the_study = stability.study(args.scenes, args.integrators, workers=args.jobs, budget=common.budget(args))
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, ("stability.csv", "stability.md", "stability.png", "README.md"))
    return study.run(the_study, out, command=common.command(args), fresh=args.fresh, log=_log)


def add_stability(sub) -> None:
    st = sub("stability", "stability map of the hard scenes: largest stable dt (fixed step), step statistics "
                          "(adaptive) -> --out")
    common.add_scenes(st, "the hard scenes of the map (default: all eight)")
    common.add_integrators(st, "(default: the project's own methods, implicit baselines last; a plugin runs when "
                               "named)", registered=False)  # the study checks its own names
    common.add_jobs(st, common.DEFAULT_JOBS.format(unit="scene and method"))
    common.add_budget(st, "the map goes on (such a row is recomputed on resume)")
    common.add_fresh(st, "OUT/stability.csv")
    common.add_out(st, "output directory (created if missing)", default=str(policy.STABILITY_DIR))
    st.set_defaults(func=cmd_stability)
