"""`python -m benchmark work-rule`: the flop rule against compiled floors
(`benchmark.work.work_rule`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar


def cmd_work_rule(args) -> int:
    """The flop rule against compiled floors (`benchmark.work.work_rule`); --floor, --elements and
    --steps are checked by their parse functions."""
    out = None if args.out == "-" else opt.writable_file(args.out)  # --out -: print only
    from reelbench.benchmark.work import work_rule
    from reelbench.models.io import atomic_write_text

    text = work_rule.report(args.floor, args.elements, args.steps, args.repeats, command=common.command(args))
    if out is None:
        print(text)
    else:
        atomic_write_text(out, text)
        _log(f"wrote {out}")
    return 0


def add_work_rule(sub) -> None:
    from reelbench.benchmark.work import work_rule  # constants only (no JAX)

    w = sub("work-rule", "the flop rule against compiled floors: does the work column charge methods in the "
                         "proportion their compiled steps take time? -> --out (results/work_rule.md)",
            "The flops of one step by the project's rule (benchmark/work/flops.py), and by the earlier rule, against "
            "the time of one step of numba floors of the same equations kept outside the repository (--floor), "
            "timed interleaved; the floors' own flops counted exactly (benchmark/work/opcount.py). Pin one core "
            "(taskset -c 0) on a quiet machine: floor times on a loaded one are noisy.")
    w.add_argument("--floor", required=True, type=common.as_type(work_rule.floor_dir, "floor directory"),
                   help=f"directory of the numba floors ({', '.join(work_rule.FLOORS)})")
    common.add_elements(w, "", least=2, default=common.csv_of(work_rule.ELEMENTS))
    w.add_argument("--steps", type=common.ruled(opt.positive_int, work_rule.check_steps, "steps"),
                   default=work_rule.STEPS, help="steps per timed floor run at N = 10, fewer in proportion above")
    w.add_argument("--repeats", type=opt.positive_int, default=work_rule.REPEATS, help="interleaved repeats (the "
                                                                                       "least time counts)")
    common.add_out(w, "the Markdown table; - = only print it", default=str(policy.WORK_RULE_FILE))
    w.set_defaults(func=cmd_work_rule)
