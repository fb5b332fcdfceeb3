"""`python -m benchmark xval`: the cross-validation against MoorDyn and MuJoCo
(`benchmark.studies.xval`), its scene checked as translatable, on the one study runner
(`benchmark.core.study.run`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError


def cmd_xval(args) -> int:
    """Cross-validation against MoorDyn and MuJoCo; exit 2 on a scene it cannot translate."""
    import importlib.util

    from reelbench.benchmark.core import study
    from reelbench.benchmark.studies import xval
    from reelbench.models import load_scene

    scene = load_scene(args.scene, **({"t_end": args.t_end} if args.t_end else {}))  # plausible horizon
    unknown = [c for c in args.cases or () if c not in xval.CASES]
    if unknown:
        raise UsageError(f"--cases {common.csv_of(unknown)}: allowed {common.csv_of(xval.CASES)}")
    xval.check_scene(scene)  # names what cannot be translated, before any work
    t_end = args.t_end or xval.DEFAULT_T_END
    opt.check_size(scene, t_end, xval.OUTPUT_INTERVAL, what=f"xval of {scene.name}", save_option=None)
    out = opt.writable_dir(args.out)
    missing = [m for m in ("moordyn", "mujoco") if importlib.util.find_spec(m) is None]
    if missing:
        raise UsageError(f"xval needs {', '.join(missing)}: pip install 'reelbench[xval]'")
    opt.no_directory_at(out, (xval.TABLE, "tips.npz", "settings.json", "README.md"))
    # two or more N >= 2 (parsed)
    the_study = xval.study(args.scene, args.elements or list(xval.DEFAULT_ELEMENTS), t_end, out, cases=args.cases,
                           log=_log)
    return study.run(the_study, out, command=common.command(args), fresh=args.fresh, log=_log)


def add_xval(sub) -> None:
    xv = sub("xval", "cross-validation against MoorDyn and MuJoCo at equal N -> --out (needs the [xval] extra)")
    common.add_scenes(xv, "a fixed-length scene", one=True, default="fixed_length")
    common.add_elements(xv, "two or more N >= 2 (default: 5,10,20,40,80; 5,10,20,40,80,160 takes about 4x longer)",
                        least=2, two_or_more=True)
    common.add_t_end(xv, "(default: 5)")
    xv.add_argument("--cases", type=opt.names, help="comma-separated cases of point_mass, rigid_body, in_water "
                                                    "(default: every case the scene has)")
    common.add_fresh(xv, "OUT/cost.csv")
    common.add_out(xv, "output directory (created if missing)", default=str(policy.XVAL_DIR))
    xv.set_defaults(func=cmd_xval)
