"""The work of a run in one unit: floating-point operations (the ``flops`` column of runs.csv).

**One rule for every method:** a run's flops are its (attempted) steps × the flops of its
**whole compiled step** by XLA's cost model (``compiled.cost_analysis()``): the stage
arithmetic, the right-hand sides inside it, Lie group exponentials, the error estimator and the
step-size controller, as one compiled function, so that every method is charged what its step
computes and nothing is summed from pieces counted apart (XLA's count is not additive: one
right-hand side alone is 1,380 flops at N = 10, but its cost in a step follows from the fusion
around it). XLA counts the body of a loop once, so the step's loops are multiplied by their
trip counts here: a ``scan`` by its length, a ``while_loop`` by its measured trips (the Newton
iteration at the run's mean Newton iterations per (sub)step; the stage loop of diffrax's
Runge–Kutta step at its stages evaluated per step). By kind of method:

* a fixed-step method with a compiled step (``init`` / ``step``: the LGVI family, RATTLE,
  ``lie_rk4``, ``crouch_grossman3``, plugins): ``steps`` × that step (`step_cost`), `FROM_STEP`;
* diffrax's explicit pairs (``tsit5``, ``dopri5``, ``dopri8``): attempted steps × diffrax's
  ``solver.step`` plus, adaptive, its PID controller's ``adapt_step_size`` (`diffrax_step_cost`),
  and the start's extra evaluations (first stage, initial step size) × one right-hand side,
  `FROM_DIFFRAX`;
* scipy's explicit pairs (``rk45``, ``dop853``, ``rk45_projected``): their **compiled twin**
  (`scipy_twin_step`): scipy's ``rk_step``, error norm and step-factor update written in JAX
  with scipy's own tableau arrays (``A``, ``B``, ``C``, ``E`` / ``E3``, ``E5``) and the same
  right-hand side, so the Python interpreter between scipy's calls (not arithmetic) is left out
  and the arithmetic is counted like every other step's; attempted steps × that step, + the
  start's evaluations, `FROM_TWIN`;
* the rest (``radau``; ``kvaerno5`` when counted), whose step is a Newton iteration of
  library code outside one compiled function: ``rhs_evals`` × one compiled right-hand side +
  ``jac_evals`` × one compiled Jacobian + ``lu_decompositions`` × (2/3) ny³, `FROM_RHS`, which
  the note says is not the whole-step rule.

The rule is checked against compiled floors (numba implementations of the same steps):
`benchmark.work.work_rule`, results/work_rule.md. Where a count cannot be had the row gets no
number and ``flops_note`` says why (never a zero). Compiled pieces are cached per process
(model, method, right-hand side).
"""

from __future__ import annotations

import functools
import hashlib
import json

import numpy as np

#: What ``flops_note`` says for each way of counting.
FROM_RHS = ("XLA cost_analysis of one right-hand side x rhs_evals (+ Jacobians, + (2/3) ny^3 per LU): "
            "not the whole-step rule (a library's implicit step)")
FROM_STEP = "XLA cost_analysis of one whole step, loops x trip counts (Newton loops at the run's mean iterations)"
FROM_DIFFRAX = ("XLA cost_analysis of one whole diffrax step (solver.step, + the PID controller when adaptive; "
                "stage loop x its stages) x attempted steps, + the start's evaluations x one right-hand side")
FROM_TWIN = ("XLA cost_analysis of the compiled twin of scipy's step (its tableau, error norm and step factor in "
             "JAX) x attempted steps, + the start's evaluations x one right-hand side")


#: Which program XLA's cost model counts: "compiled", the optimised executable (what runs:
#: XLA's fusion recomputes some values inside several fused kernels instead of storing them,
#: and those recomputations are counted, so one right-hand side alone is 1,380 flops at
#: N = 10 but two chained are 4,648), or "lowered", the program as written before optimisation
#: (each operation once, additive: 1,157 and 2,448). runs.csv uses this one, "lowered": it is the
#: same on every machine (the optimised program depends on the CPU XLA compiles for) and each
#: operation is counted once. `benchmark.work.work_rule` checks both against the compiled floors
#: (results/work_rule.md). Neither keeps every method pair within 1.5x of the floors' time ratio
#: (quiet pinned core, 2026-12-05, three runs: lowered 12 of 18 pairs at N = 10, 40, 160 every
#: time, compiled 13-14), and no count of flops can: the floors' own flops, counted exactly
#: (`benchmark.work.opcount`), keep 15-16, for the floors run at 2.8-5.4 GFlop/s by kind of
#: arithmetic (lie_rk4 / lgvi and dopri8 / lie_rk4 at N = 160 miss in every run). The rest of
#: the lowered count's misses is what the programs compute: diffrax's stage sums run over every
#: stage, zeros of the tableau included, so its tsit5 and dopri8 steps count 1.2-1.9x the floors'
#: flops, the LGVI step 1.1-1.3x and lie_rk4's 0.9-1.4x.
PROGRAM_COUNT = "lowered"
PROGRAM_COUNTS = ("compiled", "lowered")


def use_program_count(which: str) -> None:
    """Count ``which`` program from now on (`PROGRAM_COUNT`), dropping the cached counts."""
    global PROGRAM_COUNT
    if which not in PROGRAM_COUNTS:
        raise ValueError(f"program count must be one of {PROGRAM_COUNTS}, got {which!r}")
    PROGRAM_COUNT = which
    for cached in (rhs_flops, step_cost, diffrax_step_cost, scipy_twin_step):
        cached.cache_clear()


#: The source a count depends on (besides the scene's physics and JAX's version).
COUNT_CODE = (("models", "integrators"), ("benchmark/work/flops.py",))


def _count_path(fn_name: str, args: tuple):
    """Where a count is kept on disk (None: not kept), beside JAX's compiled programs
    (`models._jax.compile_cache_dir`, off with it): one JSON file per count, named by what
    determines it, so that every worker process and every later run reads a count once traced."""
    from reelbench.models._jax import compile_cache_dir, jax, xla_flags
    from reelbench.models.io import inside, user_cache_dir
    from reelbench.benchmark.core.store import source_hash

    if compile_cache_dir() is None:
        return None
    if isinstance(args[0], str):  # a method's step: kept only when its code is in COUNT_CODE (not a plugin's)
        from reelbench.integrators import get_integrator

        if not type(get_integrator(args[0])).__module__.startswith(tuple(f"reelbench.{d}." for d in COUNT_CODE[0])):
            return None
    what = [a.scene.key() if hasattr(a, "scene") else a for a in args]
    key = json.dumps({"count": fn_name, "args": what, "program": PROGRAM_COUNT, "jax": jax.__version__,
                      "xla_flags": xla_flags() if PROGRAM_COUNT == "compiled" else "",
                      "code": source_hash(*COUNT_CODE)}, sort_keys=True)
    return inside(user_cache_dir() / "flops", f"{fn_name}-{hashlib.sha256(key.encode()).hexdigest()[:20]}.json")


def _tupled(value):
    """``value`` with every list a tuple (JSON reads tuples back as lists)."""
    return tuple(_tupled(v) for v in value) if isinstance(value, (list, tuple)) else value


def _kept_on_disk(count):
    """``count(*args)``, read from its file when one was written (`_count_path`), else traced
    and written. Tracing a step and asking XLA for its cost takes 0.3-6 s a method and scene; a
    count is a pure function of the code, the physics and JAX, so it is kept like a compiled
    program. A file that cannot be read or written costs a recount, never the row."""
    from reelbench.models.io import WriteFailed, atomic_write_text

    @functools.wraps(count)
    def kept(*args):
        path = _count_path(count.__name__, args)
        if path is not None:
            try:
                return _tupled(json.loads(path.read_text()))
            except (OSError, ValueError):
                pass
        value = _tupled(count(*args))
        if path is not None:
            try:
                atomic_write_text(path, json.dumps(value))
            except WriteFailed:
                pass
        return value

    return kept


def _counted(lowered):
    return lowered.compile() if PROGRAM_COUNT == "compiled" else lowered


def xla_flops(fn, *args) -> float:
    """Flops of ``fn(*args)`` by XLA's cost model of the function's program (`PROGRAM_COUNT`;
    loops counted once)."""
    from reelbench.models._jax import jax

    return compiled_flops(_counted(jax.jit(fn).lower(*args)))


def compiled_flops(compiled) -> float:
    """The ``flops`` of a lowered (or compiled) function's ``cost_analysis()`` (a dict, or a list of one)."""
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", np.nan))


@functools.lru_cache(maxsize=64)
@_kept_on_disk
def rhs_flops(model, rhs: str, jacobian: bool = False) -> float:
    """Flops of one evaluation of the right-hand side ``rhs`` (``jacobian``: of one forward-mode
    Jacobian of it). Through the jitted functions the scipy methods call (`integrators.rhs`),
    so that after such a run the executable is already compiled (a cache hit, not a compile)."""
    from reelbench.integrators.rhs import jacobian_jit, rhs_jit

    f = (jacobian_jit if jacobian else rhs_jit)(model, rhs)
    return compiled_flops(_counted(f.lower(0.0, np.asarray(model.initial_ode_state(), dtype=float))))


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

    from reelbench.models._jax import jax

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
@_kept_on_disk
def step_cost(name: str, model, rhs: str | None = None) -> tuple[float, tuple, bool]:
    """(XLA's one-pass flops of one step, its loop terms, whether it has an uneven cond
    (`has_uneven_cond`)) of the fixed-step method ``name`` (``rhs``: the right-hand side its
    ``ode.f`` is, for a method that uses one)."""
    from reelbench.models._jax import jax
    from reelbench.integrators import get_integrator
    from reelbench.integrators.lifecycle import ODEProblem

    from reelbench.integrators.rhs import DEFAULT_RHS, ode_rhs

    integ = get_integrator(name)
    f = ode_rhs(model, rhs or DEFAULT_RHS) if getattr(integ, "uses_rhs", False) else None
    params = integ.run_parameters(integ.check_options({}))
    # what ``init`` starts from: the ODE state by default (`FixedStepMethod.initial_state`);
    # the LGVI family overrides it with (x, R, p), p shaped like w
    from reelbench.integrators.fixed_step import FixedStepMethod

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


def _ode_term_and_state(model, rhs: str):
    from reelbench.models._jax import jnp

    from reelbench.integrators.rhs import ode_rhs

    return ode_rhs(model, rhs), jnp.asarray(model.initial_ode_state(), dtype=float)


@functools.lru_cache(maxsize=64)
@_kept_on_disk
def diffrax_step_cost(name: str, model, rhs: str, adaptive: bool) -> float:
    """Flops of one attempted step of the diffrax explicit pair ``name``: diffrax's
    ``solver.step`` (its stage loop, a while loop, at the stages it evaluates per step) plus,
    when ``adaptive``, the PID controller's ``adapt_step_size`` (error norm, factor)."""
    import diffrax as dfx

    from reelbench.models._jax import jax
    from reelbench.integrators import get_integrator

    integ = get_integrator(name)
    f, y0 = _ode_term_and_state(model, rhs)
    term = dfx.ODETerm(lambda t, y, args: f(t, y))
    solver = integ.make_solver(1e-6, 1e-8)
    state0 = solver.init(term, 0.0, 1e-3, y0, None)
    controller = dfx.PIDController(rtol=1e-6, atol=1e-8)
    order = solver.order(term)
    ctrl0 = controller.init(term, 0.0, 1e-3, y0, 1e-3, None, solver.func, order)[1]

    def step(y, state, h, ctrl):
        y1, y_error, _, state1, _ = solver.step(term, 0.0, h, y, None, state, made_jump=False)
        if not adaptive:
            return y1, state1
        return y1, state1, controller.adapt_step_size(0.0, h, y, y1, None, y_error, order, ctrl)

    closed = jax.make_jaxpr(step)(y0, state0, 1e-3, ctrl0)
    stages = integ.fsal_stages - 1  # the stage loop's trips: the evaluations of one step
    return _body_flops(closed) + extra_flops(loop_terms(closed), float(stages))


#: scipy's step-size update (scipy.integrate._ivp.rk): factor = min(MAX, SAFETY × norm^exponent)
_SAFETY, _MAX_FACTOR = 0.9, 10.0


@functools.lru_cache(maxsize=64)
@_kept_on_disk
def scipy_twin_step(name: str, model, rhs: str) -> float:
    """Flops of one attempted step of scipy's explicit pair behind ``name`` (RK45, DOP853),
    as its compiled twin: scipy's ``rk_step`` (stages from the tableau ``A``, ``B``, ``C``,
    FSAL), the error norm (``E``; DOP853: ``E3`` and ``E5``) and the step factor, in JAX with
    scipy's own arrays and the same right-hand side."""
    from reelbench.models._jax import jnp

    from reelbench.integrators import get_integrator

    cls = get_integrator(name).solver_class
    A, B, C, n = np.asarray(cls.A), np.asarray(cls.B), np.asarray(cls.C), int(cls.n_stages)
    exponent = -1.0 / (cls.error_estimator_order + 1)
    two_estimates = hasattr(cls, "E5")
    f, y0 = _ode_term_and_state(model, rhs)

    def step(t, y, f0, h, rtol, atol):
        K = [f0]
        for s_ in range(1, n):
            K.append(f(t + C[s_] * h, y + jnp.dot(jnp.stack(K).T, A[s_, :s_]) * h))
        y_new = y + h * jnp.dot(jnp.stack(K).T, B)
        K.append(f(t + h, y_new))
        Kt = jnp.stack(K).T
        scale = atol + jnp.maximum(jnp.abs(y), jnp.abs(y_new)) * rtol
        if two_estimates:  # DOP853._estimate_error_norm
            e5, e3 = jnp.dot(Kt, cls.E5) / scale, jnp.dot(Kt, cls.E3) / scale
            n5, n3 = jnp.sum(e5 ** 2), jnp.sum(e3 ** 2)
            norm = jnp.abs(h) * n5 / jnp.sqrt((n5 + 0.01 * n3) * y.size)
        else:  # RungeKutta._estimate_error_norm: rms of (K^T E h) / scale
            norm = jnp.sqrt(jnp.mean((jnp.dot(Kt, cls.E) * h / scale) ** 2))
        return y_new, K[-1], jnp.minimum(_MAX_FACTOR, _SAFETY * norm ** exponent)

    f0 = f(0.0, y0)
    return xla_flops(step, 0.0, y0, f0, 1e-3, 1e-6, 1e-8)


#: Flops of renormalising a quaternion (4 squares, 3 adds, a square root, 4 divisions): the
#: projection ``rk45_projected`` adds after every accepted step, beside one more evaluation.
QUATERNION_PROJECTION_FLOPS = 12.0


def _is_scipy_pair(integ) -> bool:
    try:
        from scipy.integrate._ivp.rk import RungeKutta

        cls = getattr(integ, "solver_class", None)
        return isinstance(cls, type) and issubclass(cls, RungeKutta)
    except Exception:  # not scipy's, or scipy's layout changed: the evaluation rule
        return False


def counting_rule(integrator) -> str:
    """How `run_flops` counts ``integrator``'s work (a registered name, or the integrator):
    "step" (its compiled step), "diffrax" (diffrax's step), "twin" (the compiled twin of scipy's
    explicit step): the whole-step rule; or "evaluations" (`FROM_RHS`: right-hand sides, Jacobians
    and LU factorisations, which leaves out the step's own arithmetic, e.g. Radau's Newton solves:
    a lower bound of its work)."""
    from reelbench.integrators import get_integrator

    integ = get_integrator(integrator) if isinstance(integrator, str) else integrator
    if hasattr(integ, "step") and hasattr(integ, "init"):
        return "step"
    if getattr(integ, "fsal_stages", 0):
        return "diffrax"
    if _is_scipy_pair(integ):
        return "twin"
    return "evaluations"


#: The rules that count a method's whole step (`counting_rule`).
WHOLE_STEP_RULES = ("step", "diffrax", "twin")


def run_flops(integrator: str, model, stats: dict, rhs: str | None, adaptive: bool | None = None
              ) -> tuple[float, str]:
    """(flops of a run, how they were counted or why there are none) from its stats, by the
    one rule of the module's docstring. ``adaptive``: whether the run was adaptive (a diffrax
    pair's controller is in its step then); None: from the stats (its extra start evaluations)."""
    def count(key):
        v = stats.get(key)
        return float(v) if v is not None and np.isfinite(v) else None

    evals, steps = count("rhs_evals"), count("steps")
    try:
        if stats.get("counts_unavailable"):
            return np.nan, f"no flops: {stats['counts_unavailable']}"
        from reelbench.integrators import get_integrator

        integ = get_integrator(integrator)
        rule = counting_rule(integ)
        if rule == "step":
            if steps is None:
                return np.nan, "no flops: the method reports no step count"
            return _compiled_step_flops(integrator, integ, model, stats, rhs, steps)
        attempted = count("attempted_steps")
        if attempted is None and steps is not None and count("rejected_steps") is not None:
            attempted = steps + count("rejected_steps")
        stages = getattr(integ, "fsal_stages", 0)
        if rule == "diffrax" and rhs and evals is not None and attempted is not None:
            start = evals - (stages - 1) * attempted  # 1 (first stage), + 2 (initial step size) when adaptive
            per_step = diffrax_step_cost(integrator, model, rhs, bool(start > 1) if adaptive is None else adaptive)
            return attempted * per_step + max(start, 0.0) * rhs_flops(model, rhs), FROM_DIFFRAX
        if rule == "twin" and rhs and evals is not None and attempted is not None:
            start = evals - integ.solver_class.n_stages * attempted  # the first f and the initial step's
            total = attempted * scipy_twin_step(integrator, model, rhs) + max(start, 0.0) * rhs_flops(model, rhs)
            if getattr(integ, "projected", False) and model.layout.has_attitude:
                total += steps * (rhs_flops(model, rhs) + QUATERNION_PROJECTION_FLOPS)
            return total, FROM_TWIN
        if evals is not None and rhs:
            ny, jacs = model.layout.ny, count("jac_evals") or 0.0
            total = evals * rhs_flops(model, rhs) + (jacs * rhs_flops(model, rhs, True) if jacs else 0.0)
            total += (count("lu_decompositions") or 0.0) * (2.0 / 3.0) * ny ** 3
            return total, FROM_RHS
        return np.nan, "no flops: the method reports neither RHS evaluations nor a compiled step"
    except Exception as exc:  # a count that fails must not lose the row
        return np.nan, f"no flops: counting failed ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"


def _compiled_step_flops(integrator: str, integ, model, stats: dict, rhs: str | None, steps: float
                         ) -> tuple[float, str]:
    """steps × the whole compiled step, its while loops at the run's mean Newton iterations."""
    newton = stats.get("newton_iterations")
    newton = float(newton) if newton is not None and np.isfinite(newton) else None
    base, terms, uneven = step_cost(integrator, model, rhs if getattr(integ, "uses_rhs", False) else None)
    scheme = getattr(integ, "scheme", None)
    substeps = scheme.substeps if scheme is not None else 1
    per_solve = (newton or steps * substeps) / max(steps * substeps, 1.0)
    note = FROM_STEP
    if newton is None and _has_while(terms):
        note += "; this method reports no iteration count: its while loops counted once per step (a lower bound)"
    if uneven:
        note += ("; a branch taken only on some steps or iterations (a fallback solve, a Jacobian refresh) is counted "
                 "every time: an upper bound")
    return steps * (base + extra_flops(terms, per_solve)), note
