"""The solve budget a study's job carries (`benchmark.runs.runner.SolveBudget`: the commands'
--max-steps and --time-limit), as its solves take it and as its resume key holds it.

A job's ``budget`` is None for the defaults (`benchmark.core.policy.SOLVE_MAX_STEPS` and
`SOLVE_TIME_LIMIT`). A budgeted solve is the unbudgeted one, bit for bit, until the budget runs
out (`integrators.lifecycle.run_in_chunks`), so the defaults add nothing to a key (a row's key is
what it was before the budgets were options, for the same study code), and a row made under
another budget is recomputed when the defaults are asked for again.
"""

from __future__ import annotations


def of(budget):
    """``budget``, or the default one for None."""
    from reelbench.benchmark.runs.runner import SolveBudget  # here: the command line reads the studies without it

    return budget if budget is not None else SolveBudget()


def solve_kwargs(budget) -> dict:
    """The ``max_steps`` and ``time_limit`` of `Integrator.solve` for ``budget`` (None: the defaults)."""
    return of(budget).solve_kwargs()


def key_settings(budget) -> dict:
    """What ``budget`` adds to a job's key: nothing at the defaults, else both of its values."""
    if budget is None:
        return {}
    from reelbench.benchmark.runs.runner import SolveBudget

    b = of(budget)
    return {} if b == SolveBudget() else {"max_steps": b.max_steps, "time_limit": b.time_limit}
