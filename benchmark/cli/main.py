"""Command line: ``python -m benchmark {run,check,simulate,figures,speed,stability,answer,xval,reel-reversal,orders,energy,verify,work-rule,list}``
(also ``reelbench``).

Every command checks all of its input first -- option types and ranges, conflicting options,
integrator and study names, the scene (and the plausibility of its values), the output place
(proved writable, but created only when the work starts, so a refused command leaves no
--out behind) and the size of the run -- and only then imports JAX and calls its pipeline,
which lives with what it does (`benchmark.studies.grid.run_sweep`, `benchmark.core.study.run`
for the studies on the one runner, `benchmark.studies.check.run_check`, ...). A mistake is
answered in well under a second with ``error: ...`` and exit status 2, without a traceback
(set REELBENCH_DEBUG=1 to see where a ValueError came from); a file-system fault during the
work (a full disk, a read-only place) is one ``error: cannot write FILE: ...`` line and exit
status 1, with the rows finished so far kept; any other exception is an internal error and
keeps its traceback. Ctrl-C or SIGTERM stops every command with one line saying what was saved
(exit status 130 or 143).

The options that several commands share (--scenes, --integrators, --jobs, --fresh, the solve
budgets, --executor, --set, --t-end, --elements, --out) are declared once, with their help, default
and parse function, in `benchmark.cli.common`. Each command is one module of `benchmark.cli`
(`simulate` holds `figures` too): its parser builder (`add_*`, calling the shared options it has)
and its function (`cmd_*`: the checks, then the pipeline).

The model and the scene format: models/README.md. The integrators: integrators/README.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading

from reelbench.benchmark.cli import (answer, check, common, energy, listing, orders, reel_reversal, run, simulate, speed,
                           stability, verify, work_rule, xval)
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.models.io import printable

#: The commands, in the order `--help` lists them.
BUILDERS = (run.add_run, check.add_check, simulate.add_simulate, simulate.add_figures, speed.add_speed,
            stability.add_stability, answer.add_answer, xval.add_xval, reel_reversal.add_reel_reversal,
            orders.add_orders, energy.add_energy, verify.add_verify, work_rule.add_work_rule, listing.add_list)


class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except where there is none to show (None, a flag's False)."""

    def _get_help_string(self, action):
        if action.default in (None, False) or isinstance(action, argparse._HelpAction):
            return action.help
        return super()._get_help_string(action)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmark", description=__doc__, formatter_class=_Help)
    commands = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def sub(name: str, help: str, description: str | None = None) -> argparse.ArgumentParser:
        return commands.add_parser(name, help=help, description=description or help, formatter_class=_Help)

    for add in BUILDERS:
        add(sub)
    return p


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        try:
            args = parser().parse_args(argv)
        except SystemExit as exc:  # --help (0) or a bad option (2, argparse printed "error: ...")
            return exc.code if isinstance(exc.code, int) else 2
        args.argv = argv
        common.run_checks(args)  # the checks that need a second option (`common.add_check`)
        if threading.current_thread() is threading.main_thread():
            from reelbench.benchmark.core.engine import install_stop_handlers

            install_stop_handlers()  # SIGTERM stops every command like Ctrl-C: one line, exit 143
        return args.func(args)
    except ValueError as exc:  # bad input (UsageError, SceneError, an integrator's argument check)
        if os.environ.get("REELBENCH_DEBUG"):  # a developer chasing a ValueError gets its traceback
            raise
        _log(f"error: {printable(exc)}")  # input quoted in it (a path with a newline, U+202E) stays one line
        return 2
    except OSError as exc:  # the file system failed during work (full, read-only, ...): no traceback
        if os.environ.get("REELBENCH_DEBUG"):
            raise
        _log(f"error: {printable(exc)}")
        return 1
    except KeyboardInterrupt as exc:  # a command without its own stop message
        from reelbench.benchmark.core.engine import stop_cause, stop_status

        _log(f"stopped by {stop_cause(exc)}: no result was written (this command writes its results when it ends)")
        return stop_status(exc)
