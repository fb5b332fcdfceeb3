"""`python -m benchmark energy`: the long-horizon energy study (`benchmark.studies.horizon`), on the
one study runner (`benchmark.core.study.run`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar


def cmd_energy(args) -> int:
    from reelbench.benchmark.core import study
    from reelbench.benchmark.studies import horizon
    from reelbench.models import load_scene

    for sc in args.scenes or ():
        load_scene(sc)
    horizon.methods(args.integrators)  # an unknown name is refused (one outside the plan makes no runs)
    variants = tuple(args.variants) if args.variants else tuple(horizon.VARIANTS)
    unknown = [v for v in variants if v not in horizon.VARIANTS and v != "plain"]
    if unknown:
        raise ValueError(f"unknown string variant(s) {', '.join(unknown)}: choose from plain, "
                         + ", ".join(v for v in horizon.VARIANTS if v))
    the_study = horizon.study(args.horizon, args.scenes, selected=args.integrators, workers=args.jobs, text=True,
                              variants=tuple("" if v == "plain" else v for v in variants), budget=common.budget(args))
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, (horizon.TABLE, "energy_horizon.md", "README.md"))
    if not the_study.jobs:
        _log("horizon: none of the selected methods is in the energy study's plan; nothing written")
        return 0
    return study.run(the_study, out, command=common.command(args), fresh=args.fresh, log=_log)


def add_energy(sub) -> None:
    from reelbench.benchmark.studies import horizon  # constants only (no JAX)

    e = sub("energy", "the long-horizon energy study: energy error vs time beside the axial vibration and "
                      "the least tension, the modified-energy offset told apart from drift -> "
                      "OUT/energy_horizon.csv, figures and OUT/energy_horizon.md",
            "The energy study (benchmark/studies/horizon.py): the runs of its plan (horizon.PLAN: methods, N = "
            f"{common.csv_of(horizon.ELEMENTS)}, each method's setting in horizon.SETTINGS and {horizon.FINER:g}x finer), "
            "on each scene and with the tension-only string (`slack`); the histories already in "
            "OUT/energy_horizon.csv for the same settings and code are kept, rows of other methods and scenes too.")
    common.add_scenes(e, f"(default: {horizon.DEFAULT_SCENE})")
    common.add_integrators(e, "(default: every method of the study's plan)", registered=False)
    e.add_argument("--horizon", type=opt.positive_float, default=horizon.HORIZON, help="length in s")
    e.add_argument("--variants", type=opt.names, help="comma-separated string laws: plain (the scene as it is), "
                                                      "slack (tension-only) (default: both)")
    common.add_jobs(e, common.DEFAULT_JOBS.format(unit="run"))
    common.add_budget(e, "its history up to there is tabled with that status")
    common.add_fresh(e, "OUT/energy_horizon.csv")
    common.add_out(e, "output directory (created if missing)", default=str(policy.RESULTS))
    e.set_defaults(func=cmd_energy)
