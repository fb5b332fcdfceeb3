"""The work of a run in one unit: floating-point operations (the ``flops`` column of runs.csv).

A run's flops are its counts times what XLA's cost model (``compiled.cost_analysis()``) says
one counted unit costs, so that one Newton iteration of the LGVI and one right-hand side of a
Runge–Kutta method are no longer both "1":

* a method that counts right-hand-side evaluations: ``rhs_evals`` × the flops of one compiled
  evaluation of the right-hand side it ran (``rhs`` column), plus ``jac_evals`` × one compiled
  forward-mode Jacobian, plus ``lu_decompositions`` × (2/3) ny³ (a dense LU, counted, since
  scipy factors outside XLA);
* a fixed-step method that counts no evaluations (the LGVI family, RATTLE): ``steps`` × the
  flops of one compiled step. XLA's cost model counts the body of a loop once, so the step's loops are
  multiplied by their trip counts here: a ``scan`` by its length, a ``while_loop`` (the Newton
  iteration, the symmetric scheme's forcing fixed point) by the run's mean Newton iterations
  per (sub)step, which is exact for the one Newton loop of the paper's LGVI (a method that
  reports no iteration count gets its while loops once per step, and its note says so).

Where a count cannot be had the row gets no number and ``flops_note`` says why (never a zero).
Compiled pieces are cached per process (model, method, right-hand side).
"""

from __future__ import annotations

import functools

import numpy as np

#: What ``flops_note`` says for each way of counting.
FROM_RHS = "XLA cost_analysis of one right-hand side x rhs_evals (+ Jacobians, + (2/3) ny^3 per LU)"
FROM_STEP = "XLA cost_analysis of one step, loops x trip counts (Newton loops at the run's mean iterations)"


def xla_flops(fn, *args) -> float:
    """Flops of ``fn(*args)`` by XLA's cost model of the compiled function (loops counted once)."""
    from models._jax import jax

    return compiled_flops(jax.jit(fn).lower(*args).compile())


def compiled_flops(compiled) -> float:
    """The ``flops`` of a compiled executable's ``cost_analysis()`` (a dict, or a list of one)."""
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", np.nan))


@functools.lru_cache(maxsize=64)
def rhs_flops(model, rhs: str, jacobian: bool = False) -> float:
    """Flops of one evaluation of the right-hand side ``rhs`` (``jacobian``: of one forward-mode
    Jacobian of it). Through the jitted functions the scipy methods call (`integrators.rhs`),
    so that after such a run the executable is already compiled (a cache hit, not a compile)."""
    from integrators.rhs import jacobian_jit, rhs_jit

    f = (jacobian_jit if jacobian else rhs_jit)(model, rhs)
    return compiled_flops(f.lower(0.0, np.asarray(model.initial_ode_state(), dtype=float)).compile())


def _sub_jaxprs(eqn):
    """The closed jaxprs an equation calls (jit, custom rules, a cond's branches, a loop's body
    and condition)."""
    from jax.extend import core

    out = []
    for v in eqn.params.values():
        for item in v if isinstance(v, (list, tuple)) else (v,):
            if isinstance(item, core.ClosedJaxpr):
                out.append(item)
            elif isinstance(item, core.Jaxpr):
                out.append(core.ClosedJaxpr(item, ()))
    return out


def _body_flops(closed) -> float:
    from jax.extend import core

    from models._jax import jax

    args = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in closed.in_avals]
    return xla_flops(core.jaxpr_as_fun(closed), *args)


def loop_terms(closed) -> list:
    """What XLA's one-pass count of ``closed`` leaves out: [(kind, trips, body flops, nested terms)]
    for every loop in it (kind "scan" with its length, or "while")."""
    terms = []
    for eqn in closed.jaxpr.eqns:
        name = eqn.primitive.name
        if name == "scan":
            body = eqn.params["jaxpr"]
            terms.append(("scan", int(eqn.params["length"]), _body_flops(body), loop_terms(body)))
        elif name == "while":
            body = eqn.params["body_jaxpr"]
            terms.append(("while", None, _body_flops(body), loop_terms(body)))
        elif name == "cond":  # the costlier branch (XLA's count takes one of them too)
            branches = [loop_terms(b) for b in eqn.params["branches"]]
            terms.extend(max(branches, key=lambda t: extra_flops(t, 1.0)))
        else:
            for sub in _sub_jaxprs(eqn):
                terms.extend(loop_terms(sub))
    return terms


def has_uneven_cond(closed, ratio: float = 2.0) -> bool:
    """Whether ``closed`` holds a cond whose branches differ in cost by more than ``ratio`` (e.g.
    RATTLE's dense exact-Jacobian fallback beside a no-op): the count takes the costlier one on
    every step, which makes the run's flops an upper bound."""
    for eqn in closed.jaxpr.eqns:
        if eqn.primitive.name == "cond":
            # a branch with no arithmetic (a pass-through) has no "flops" entry: 0
            costs = [np.nan_to_num(_body_flops(b)) + extra_flops(loop_terms(b), 1.0) for b in eqn.params["branches"]]
            if max(costs) > ratio * max(min(costs), 1.0):
                return True
        if any(has_uneven_cond(sub, ratio) for sub in _sub_jaxprs(eqn)):
            return True
    return False


def extra_flops(terms, while_trips: float) -> float:
    """Flops the loops add beyond XLA's one pass: a loop of n trips over a body B adds
    (n − 1) B + n × (what B's own loops add)."""
    total = 0.0
    for kind, trips, body, nested in terms:
        n = trips if kind == "scan" else while_trips
        total += (n - 1) * body + n * extra_flops(nested, while_trips)
    return total


@functools.lru_cache(maxsize=64)
def step_cost(name: str, model, rhs: str | None = None) -> tuple[float, tuple, bool]:
    """(XLA's one-pass flops of one step, its loop terms, whether it has an uneven cond
    (`has_uneven_cond`)) of the fixed-step method ``name`` (``rhs``: the right-hand side its
    ``ode.f`` is, for a method that uses one)."""
    from models._jax import jax
    from integrators import get_integrator
    from integrators.lifecycle import ODEProblem

    from integrators.rhs import DEFAULT_RHS, ode_rhs

    integ = get_integrator(name)
    f = ode_rhs(model, rhs or DEFAULT_RHS) if getattr(integ, "uses_rhs", False) else None
    params = integ.run_parameters(integ.check_options({}))
    # what ``init`` starts from: the ODE state by default (`FixedStepMethod.initial_state`);
    # the LGVI family overrides it with (x, R, p), p shaped like w
    from integrators.fixed_step import FixedStepMethod

    if type(integ).initial_state is FixedStepMethod.initial_state:
        y0 = np.asarray(model.initial_ode_state(), dtype=float)
    else:
        y0 = tuple(np.asarray(a, dtype=float) for a in model.initial_state())

    def step(carry, t, h, prm):
        ode = ODEProblem(model=model, f=f, layout=model.layout, params=prm)
        out = integ.step(ode, carry, t, h)
        return out

    ode0 = ODEProblem(model=model, f=f, layout=model.layout, params=params)
    carry = jax.eval_shape(lambda y: integ.init(ode0, y), y0)
    closed = jax.make_jaxpr(step)(carry, np.float64(0.0), np.float64(1e-3), params)
    return _body_flops(closed), tuple(loop_terms(closed)), has_uneven_cond(closed)


def _has_while(terms) -> bool:
    return any(kind == "while" or _has_while(nested) for kind, _, _, nested in terms)


def run_flops(integrator: str, model, stats: dict, rhs: str | None) -> tuple[float, str]:
    """(flops of a run, how they were counted or why there are none) from its stats."""
    def count(key):
        v = stats.get(key)
        return float(v) if v is not None and np.isfinite(v) else None

    evals, steps = count("rhs_evals"), count("steps")
    try:
        if evals is not None and rhs:
            ny, jacs = model.layout.ny, count("jac_evals") or 0.0
            total = evals * rhs_flops(model, rhs) + (jacs * rhs_flops(model, rhs, True) if jacs else 0.0)
            total += (count("lu_decompositions") or 0.0) * (2.0 / 3.0) * ny ** 3
            return total, FROM_RHS
        if stats.get("counts_unavailable"):
            return np.nan, f"no flops: {stats['counts_unavailable']}"
        from integrators import get_integrator

        integ = get_integrator(integrator)
        if steps is None or not (hasattr(integ, "step") and hasattr(integ, "init")):
            return np.nan, "no flops: the method reports neither RHS evaluations nor a compiled step"
        base, terms, uneven = step_cost(integrator, model, rhs if getattr(integ, "uses_rhs", False) else None)
        scheme = getattr(integ, "scheme", None)
        substeps = scheme.substeps if scheme is not None else 1
        newton = count("newton_iterations")
        per_solve = (newton or steps * substeps) / max(steps * substeps, 1.0)
        note = FROM_STEP
        if newton is None and _has_while(terms):
            note += "; this method reports no iteration count: its while loops counted once per step (a lower bound)"
        if uneven:
            note += ("; a branch taken only on some steps or iterations (a fallback solve, a Jacobian refresh) is counted "
                     "every time: an upper bound")
        return steps * (base + extra_flops(terms, per_solve)), note
    except Exception as exc:  # a count that fails must not lose the row
        return np.nan, f"no flops: counting failed ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"
