"""`python -m benchmark speed`: time per step and per right-hand-side call vs N
(`benchmark.studies.lgvi_speed`), on the one study runner (`benchmark.core.study.run`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError


def cmd_speed(args) -> int:
    from reelbench.models import load_scene

    from reelbench.benchmark.studies.lgvi_speed import SpeedRequest  # JAX-free until a measurement runs

    default = SpeedRequest()
    elements, scenes = tuple(args.elements or default.elements), tuple(args.scenes or default.scenes)
    horizon = {"t_end": args.dt * args.steps} if args.dt is not None else {}  # what each timed run covers
    for sc in scenes:  # every scene and N is checked (names, plausibility) before any work
        for n in elements:
            try:
                load_scene(sc, elements=n, **horizon)
            except ValueError as exc:
                if not horizon or "'t_end'" not in str(exc):
                    raise
                raise UsageError(f"--dt {args.dt:g} x --steps {args.steps} = {horizon['t_end']:g} s per timed run: "
                                 f"{exc}; give a smaller --dt or fewer --steps") from None
    if args.out.strip() == "-":  # each measurement is saved as it finishes: the tables always go to a file
        raise UsageError("--out -: the speed tables are saved (and printed): give a Markdown file, e.g. speed.md")
    out = opt.writable_file(args.out)
    from reelbench.benchmark.core import study
    from reelbench.benchmark.studies import lgvi_speed

    if out.is_file() and not lgvi_speed.rows_file(out).exists():
        raise UsageError(f"--out {out}: the file exists without its rows table {lgvi_speed.rows_file(out)}, "
                         "so its rows could not be kept; this run would overwrite them: give another --out, or move "
                         "it away")
    opt.no_directory_at(out.parent, (out.name, lgvi_speed.rows_file(out).name))
    from reelbench.integrators.rhs import check_rhs

    rhs = tuple(v.strip() for v in args.rhs.split(",") if v.strip())
    for r in rhs:
        check_rhs(r)
    if args.integrators:
        lgvi_speed.check_methods(args.integrators)
    request = SpeedRequest(elements=elements, scenes=scenes, methods=tuple(args.integrators) if args.integrators else None,
                           steps=args.steps, repeats=args.repeats, dt=args.dt, rhs=rhs, autodiff_max_n=args.autodiff_max_n,
                           budget=common.budget(args))
    return study.run(lgvi_speed.study(request, out), out.parent, command=common.command(args), fresh=args.fresh, log=_log)


def add_speed(sub) -> None:
    from reelbench.benchmark.studies.lgvi_speed import SpeedRequest  # JAX-free: the defaults shown in --help are the real ones

    default = SpeedRequest()
    sp = sub("speed", "time per step of every fixed-step method and per-call cost of each right-hand side vs N, "
                      "compile time separately",
             "Time per step of every fixed-step method (chosen by capability from the registry) and per-call cost "
             "of each right-hand side, vs N; compile time separately (see benchmark/studies/lgvi_speed.py).")
    common.add_elements(sp, f"(default: {common.csv_of(default.elements)})")
    common.add_scenes(sp, f"(default: {common.csv_of(default.scenes)})")
    common.add_integrators(sp, "fixed-step methods only (default: every registered one with the fixed_step "
                               "capability)", registered=False)
    sp.add_argument("--steps", type=opt.positive_int, default=default.steps, help="steps per timed run")
    sp.add_argument("--repeats", type=opt.positive_int, default=default.repeats, help="timed repeats (median)")
    sp.add_argument("--dt", type=opt.positive_float,
                    help="step size (default: per-scene stable step at N = 10, times 10/N)")
    sp.add_argument("--rhs", default=common.csv_of(default.rhs), help="right-hand sides to time per call ('' = none)")
    sp.add_argument("--autodiff-max-n", type=opt.positive_int, default=default.autodiff_max_n,
                    help="largest N for the O(N^3) autodiff right-hand side")
    common.add_budget(sp, "its measurement with it (not timed; measured again on resume): it bounds the first "
                          "solve of each measurement (compile and warm-up), the timed ones are the same work")
    common.add_fresh(sp, "the rows table beside --out")
    common.add_out(sp, "the tables (Markdown, with the command and machine; also printed): this run's rows join "
                       "those of the rows table beside it (.csv; rows of other methods, scenes and N are kept) and "
                       "the file is written from the whole table", default=str(policy.LGVI_SPEED_FILE))
    sp.set_defaults(func=cmd_speed)
