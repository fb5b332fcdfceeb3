"""The options that several commands of `python -m benchmark` share, each declared once.

A builder here adds one option (or a pair that belongs together) to a command's parser with its
name, help, default and parse function, so that every command that has the option spells,
documents, defaults and checks it the same way. The parse function is an argparse ``type=``: it
calls the rule where the rule lives (`benchmark.core.options`, `benchmark.core.policy`,
`integrators.lifecycle`, the integrator registry) and argparse names the option in a refusal
("argument --jobs: ..."). A check that needs a second option (--executor dask needs --scheduler)
is registered by the builder with `add_check` and runs after parsing, before the command.

One name per concept, on every command that has it:

* ``--scenes`` the scenes (a command that takes one scene says so and refuses two);
* ``--integrators`` the integrators (likewise for one);
* ``--jobs`` the worker processes, 0 meaning "in this process, one job after another" wherever
  a command can run its jobs so; a command that cannot refuses 0 and says why;
* ``--fresh`` recomputes what a resumable command would keep;
* ``--max-steps`` and ``--time-limit`` the budget of each solve.

The few helpers every command uses are here too (`command`, `csv_of`). Nothing here imports
JAX: `--help` and every refusal answer at once.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from typing import Callable

from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.options import UsageError


def command(args) -> str:
    """The command as the user typed it, for the headers of the files it writes."""
    return "python -m benchmark " + " ".join(shlex.quote(a) for a in args.argv)


def csv_of(values) -> str:
    """Values as one comma-separated option value (a default shown in --help, a message)."""
    return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values)


# ------------------------------------------------------------------------------------------
# Checks that need a second option: registered by a builder, run before the command
# ------------------------------------------------------------------------------------------
def add_check(p: argparse.ArgumentParser, check: Callable) -> None:
    """Run ``check(args)`` after parsing, before the command (it raises UsageError)."""
    p.set_defaults(checks=(*(p.get_default("checks") or ()), check))


def run_checks(args) -> None:
    for check in getattr(args, "checks", None) or ():
        check(args)


# ------------------------------------------------------------------------------------------
# Parse functions (argparse ``type=``)
# ------------------------------------------------------------------------------------------
def as_type(parse: Callable, name: str | None = None) -> Callable:
    """``parse`` as an argparse type: its ValueError (a rule's message: the value, the allowed
    range, a fix) becomes argparse's refusal, which names the option (argparse would otherwise
    replace the message by "invalid value")."""
    def parsed(text: str):
        try:
            return parse(text)
        except argparse.ArgumentTypeError:
            raise
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parsed.__name__ = name or parse.__name__
    return parsed


def ruled(parse: Callable, rule: Callable, name: str | None = None) -> Callable:
    """``parse`` then ``rule(value)`` (the rule where it lives; it raises ValueError with its
    message), as one argparse type."""
    def checked(text: str):
        value = parse(text)
        rule(value)
        return value

    return as_type(checked, name or parse.__name__)


def one_of(parse: Callable, what: str) -> Callable:
    """A list type that takes exactly one item: for a command that takes one ``what``."""
    def single(text: str):
        items = parse(text)
        if len(items) != 1:
            raise argparse.ArgumentTypeError(f"{text!r} names {len(items)} {what}s: this command takes one "
                                             f"(allowed: one {what}; run it once per {what})")
        return items[0]

    single.__name__ = f"one {what}"
    return single


def _registered(names: list[str]) -> None:
    from reelbench.integrators import get_integrator  # the registry: names and capabilities, no JAX

    for name in names:
        get_integrator(name)  # an unknown name: ValueError naming it, with the close match and the list


#: Comma-separated names of registered integrators (refused by name, with the available ones).
integrator_names = ruled(opt.names, _registered, "integrator names")


def jobs_in_workers(why: str) -> Callable:
    """--jobs of a command that runs its jobs in worker processes only: 0 refused, saying why."""
    def parse(text: str) -> int:
        value = opt.integer(text)
        if value < 1:
            raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: an integer >= 1)" + (
                f": 0 (in this process) is not offered here: {why}" if value == 0 else ""))
        return value

    parse.__name__ = "worker count"
    return parse


def at_least(least: int, one: bool = False) -> Callable:
    """Comma-separated integers >= ``least``, two or more unless ``one``."""
    def parse(text: str) -> list[int]:
        values = opt.integers(text)
        if any(v < least for v in values) or (not one and len(values) < 2):
            many = "one or more integers" if one else "two or more integers"
            raise argparse.ArgumentTypeError(f"{text!r} is invalid (allowed: {many} >= {least}, e.g. 5,10,20)")
        return values

    parse.__name__ = "element counts"
    return parse


# ------------------------------------------------------------------------------------------
# Builders
# ------------------------------------------------------------------------------------------
def _joined(what: str, more: str) -> str:
    """An option's help: what it is, then what this command says of it ("(default: ...)" joins
    with a space, anything else with a semicolon)."""
    return what if not more else f"{what} {more}" if more.startswith("(") else f"{what}; {more}"


def add_scenes(p, help: str, *, one: bool = False, default=None) -> None:
    """--scenes: comma-separated scene names or .toml paths; ``one``: exactly one (its value is
    then ``args.scene``, a string). The scenes themselves are loaded by the command, with its
    overrides and horizon (`models.load_scene`: names the key, the range and a fix)."""
    if one:
        p.add_argument("--scenes", dest="scene", type=one_of(opt.names, "scene"), default=default, metavar="SCENE",
                       help=_joined("one scene name or .toml path (this command takes one scene)", help))
    else:
        p.add_argument("--scenes", type=opt.names, default=default,
                       help=_joined("comma-separated scene names or .toml paths", help))


def add_integrators(p, help: str, *, one: bool = False, default=None, registered: bool = True) -> None:
    """--integrators: comma-separated integrator names; ``one``: exactly one (``args.integrator``).
    ``registered``: each name must be registered (checked here); a study with a narrower rule
    (fixed-step methods, a declared setting) checks its own."""
    names = integrator_names if registered else opt.names
    if one:
        # A string default would be parsed too (argparse), loading the registry for every refusal of
        # the command; the project's own default needs no check: it is filled in after parsing.
        shown = f"(default: {default})" if default is not None else ""
        p.add_argument("--integrators", dest="integrator", type=one_of(names, "integrator"), metavar="NAME",
                       help=_joined(_joined("one integrator name, see `list` (this command takes one)", help), shown))
        if default is not None:
            def fill(args) -> None:
                if args.integrator is None:
                    args.integrator = default

            add_check(p, fill)
    else:
        p.add_argument("--integrators", type=names, default=default,
                       help=_joined("comma-separated integrator names, see `list`", help))


#: What --jobs means on every command that has it.
JOBS = "worker processes, 0 = in this process, one job after another"
#: The default of --jobs on every study command (`engine.default_workers`), said of its unit of work.
DEFAULT_JOBS = "one per {unit}, at most the CPU count"


def add_jobs(p, default_help: str, *, default=None, workers_only: str | None = None) -> None:
    """--jobs, one meaning everywhere (`JOBS`). ``workers_only``: the command runs its jobs in
    worker processes only, and this says why 0 is refused (and what to give instead)."""
    parse, help = opt.nonnegative_int, JOBS
    if workers_only:
        parse = jobs_in_workers(workers_only)
        help = f"worker processes, >= 1 (0, in this process, is not offered here: {workers_only})"
    p.add_argument("--jobs", type=parse, default=default,
                   help=help + (f" (default: {default_help})" if default is None else ""))


def add_fresh(p, table: str) -> None:
    """--fresh: recompute every row this command would keep from ``table``."""
    p.add_argument("--fresh", action="store_true", help=f"recompute every row of this command, ignoring the rows "
                                                        f"already in {table} (default: keep the finished ones)")


def add_budget(p, what: str, *, max_steps: int | None = policy.SOLVE_MAX_STEPS,
               time_limit: float = policy.SOLVE_TIME_LIMIT) -> None:
    """--max-steps and --time-limit, the budget of each solve (`runner.SolveBudget`, defaults
    `policy.SOLVE_MAX_STEPS` and `policy.SOLVE_TIME_LIMIT` unless a command's policy says others,
    ``max_steps`` None for no step cap); ``what`` says what a solve past it leaves (a row, a saved
    trajectory)."""
    cap = "" if max_steps is not None else " (default: no step cap)"
    p.add_argument("--max-steps", type=opt.positive_int, default=max_steps,
                   help=f"step budget of each solve{cap}: a solve past it ends with status max_steps and {what}")
    p.add_argument("--time-limit", type=opt.positive_float, default=time_limit,
                   help=f"wall-clock budget of each solve in s (after compilation): a solve past it ends with status "
                        f"time_limit and {what}")


def budget(args):
    """The budget of each solve (--max-steps, --time-limit) as the runner takes it."""
    from reelbench.benchmark.runs.runner import SolveBudget

    return SolveBudget(max_steps=args.max_steps, time_limit=args.time_limit)


def _check_executor(args) -> None:
    if args.executor == "dask" and not args.scheduler:
        raise UsageError("--executor dask needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    if args.scheduler and args.executor != "dask":
        raise UsageError(f"--scheduler is only used with --executor dask (got --executor {args.executor})")


def add_executor(p, what: str) -> None:
    """--executor and --scheduler, the same on every command that runs jobs on the engine."""
    from reelbench.benchmark.runs import sweep  # constants only (no JAX)

    p.add_argument("--executor", default=sweep.DEFAULT_EXECUTOR, choices=list(sweep.EXECUTORS),
                   help=f"where {what} execute: worker processes, this process, or a Dask cluster")
    p.add_argument("--scheduler", help="Dask scheduler address, with --executor dask (e.g. tcp://host:8786)")
    add_check(p, _check_executor)


def add_set(p, help: str = "scene override, repeatable, e.g. --set elements=20") -> None:
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help=help)


def overrides(items: list[str] | None) -> dict:
    """--set key=value (value parsed as JSON when it can be: numbers, lists, quoted strings)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise UsageError(f"--set {item!r}: expected KEY=VALUE (e.g. --set elements=20)")
        k, v = item.split("=", 1)
        if not k.strip():
            raise UsageError(f"--set {item!r}: the key is empty (expected KEY=VALUE, e.g. --set elements=20)")
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
        except RecursionError:  # [[[[... thousands deep
            raise UsageError(f"--set {k.strip()}: the value is nested too deeply: a scene value is a number, "
                             f"a string or a list of at most two levels, e.g. --set direction=[0,0,1]") from None
        except ValueError:  # an integer of more digits than Python converts (int_max_str_digits)
            raise UsageError(f"--set {k.strip()}: the value holds an integer of more than "
                             f"{sys.get_int_max_str_digits()} digits: allowed a finite number of a plausible size "
                             f"(see models/README.md)") from None
    return out


def add_t_end(p, help: str, default=None) -> None:
    p.add_argument("--t-end", type=opt.positive_float, default=default, help=_joined("horizon in s", help))


def add_elements(p, help: str, *, one: bool = False, least: int = 1, two_or_more: bool = False, default=None) -> None:
    """--elements: the element counts N (comma-separated; ``one``: a single N)."""
    if one:
        parse = opt.positive_int
    elif least > 1 or two_or_more:
        parse = at_least(least, one=not two_or_more)
    else:
        parse = opt.positive_ints
    p.add_argument("--elements", type=parse, default=default,
                   help=_joined("the number of elements N" if one else "comma-separated element counts N", help))


def add_out(p, help: str, default=None) -> None:
    """--out: where the command writes (proved writable by the command, created only when the
    work starts: `options.writable_dir` / `writable_file`)."""
    p.add_argument("--out", default=default, help=help)
