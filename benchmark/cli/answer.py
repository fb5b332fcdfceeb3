"""`python -m benchmark answer`: the main job (`benchmark.answer.answer`), its scenes, methods,
sizes and targets checked, then `benchmark.answer.answer.run_answer` (its two studies on the one runner).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError


def cmd_answer(args) -> int:
    """The main job: the cheapest setting of every method at every target by search, and paired timing."""
    from reelbench.benchmark.answer import answer
    from reelbench.benchmark.runs import sweep
    from reelbench.benchmark.answer.answer import AnswerRequest
    from reelbench.models import load_scene

    targets = args.targets or tuple((m, t) for m, t, _ in answer.TARGETS)  # parsed: `_targets`
    scenes = tuple(args.scenes or (sweep.EXTENDED_SCENES if args.extended else sweep.PAPER_SCENES))
    elements = tuple(args.elements or (answer.EXTENDED_ELEMENTS if args.extended else answer.ELEMENTS))
    for sc in scenes:
        for n in elements:
            load_scene(sc, elements=n, **({"t_end": args.t_end} if args.t_end else {}))  # validated before work
    out = opt.writable_dir(args.out)
    names = tuple(args.integrators) if args.integrators else answer.default_methods(args.extended)
    return answer.run_answer(AnswerRequest(out=out, scenes=scenes, integrators=names, elements=elements,
                                           targets=targets, t_end=args.t_end, max_runs=args.max_runs,
                                           max_steps=args.max_steps, time_limit=args.time_limit,
                                           timing_budget=args.timing_budget, jobs=args.jobs, fresh=args.fresh,
                                           command=common.command(args), compare_with=tuple(args.compare_with or ()),
                                           executor=args.executor, scheduler=args.scheduler), log=_log)


def _targets(text: str) -> tuple:
    """``metric=target,...`` -> ((metric, target), ...): each metric one of the runs table's
    accuracy metrics, each target a positive number."""
    from reelbench.benchmark.runs.metrics import ACCURACY

    out = []
    for part in text.split(","):
        metric, _, value = part.strip().partition("=")
        if metric not in ACCURACY:
            raise UsageError(f"{text!r}: {metric!r} is not a metric (allowed: {', '.join(ACCURACY)}), "
                             "e.g. --targets energy_error=1e-5,position_error_final=1e-7")
        try:
            target = float(value)
        except ValueError:
            target = float("nan")
        if not (0 < target < float("inf")):
            raise UsageError(f"{text!r}: the target of {metric} must be a positive number (got {value!r})")
        out.append((metric, target))
    if len({m for m, _ in out}) != len(out):
        raise UsageError(f"{text!r}: each metric at most once (e.g. --targets energy_error=1e-5)")
    return tuple(out)


def add_answer(sub) -> None:
    from reelbench.benchmark.answer import answer
    from reelbench.benchmark.answer import search  # constants only (no JAX)

    an = sub("answer", "the main job: each method's cheapest setting at each target by search, wall-time verdicts "
                       "by paired timing -> --out/cheapest.csv, README.md, figures (and the README's answer block)",
             "For every scene x N x method x target, search the cheapest setting meeting the target that stands "
             f"(bracket, bisect to {policy.RESOLUTION * 100:g} % in cost, confirm the three settings just finer; "
             "benchmark/answer/search.py), then time the compiled methods at their settings paired and interleaved "
             "on one pinned core, racing (benchmark/answer/paired.py). Default: the paper's three scenes at N = 10 "
             "with the default methods and dopri8; --extended: every method, the scenes in water and the off-centre "
             "tow too, at N = 10 and 40, its rows merged into the same table. Resumable: rerun to continue.")
    an.add_argument("--extended", action="store_true",
                    help="every one of the project's methods on the paper's and the fluid scenes at N = 10 and 40")
    common.add_scenes(an, "(default: the paper's three)")
    common.add_integrators(an, "(default: the default sweep's and dopri8; --extended: all of the project's)")
    common.add_elements(an, "(default: 10; --extended: 10,40)")
    an.add_argument("--targets", type=common.as_type(_targets, "targets"),
                    help="comma-separated metric=target pairs on any accuracy metric of the runs table (default: "
                         f"{','.join(f'{m}={t:g}' for m, t, _ in answer.TARGETS)})")
    common.add_t_end(an, "(default: each scene's t_end)")
    an.add_argument("--max-runs", type=opt.positive_int, default=search.MAX_RUNS, help="runs per search at most")
    common.add_budget(an, "the search counts that setting as not finished (a finer one costs more)", max_steps=None,
                      time_limit=policy.SEARCH_TIME_LIMIT)
    an.add_argument("--timing-budget", type=opt.positive_float, default=policy.PAIRED_BUDGET,
                    help="seconds of paired timing per scene x N x target at most")
    common.add_jobs(an, "one per CPU", workers_only="answer searches in worker processes; --executor serial "
                                                    "searches in this process")
    common.add_executor(an, "the searches (the paired timing stays in this process, on one pinned core)")
    common.add_fresh(an, "OUT/cheapest.csv")
    an.add_argument("--compare-with", type=opt.answer_table, action="append", metavar="CHEAPEST.csv",
                    help="an earlier answer table: README.md says which answers agree (repeatable)")
    common.add_out(an, "output directory (created if missing; results/ also rewrites the README's answer)",
                   default=str(answer.COMMITTED_ANSWER))
    an.set_defaults(func=cmd_answer)
