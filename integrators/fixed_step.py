"""The fixed-step contract and its lifecycle: a method writes how one step is taken, the
lifecycle (`run_fixed_step`) does the rest, once for every fixed-step method.

* ``init(ode, y0) -> carry``: the method's state from its initial state (default: y0, the
  quaternion ODE state; a method may ask for another one with `FixedStepMethod.initial_state`);
* ``step(ode, carry, t, h)`` returns the new carry, or ``(carry, StepResult)`` when the step can
  fail or counts iterations (traced by JAX: ``jax.numpy``, no Python branches on values);
* ``state(ode, carry) -> y``: the ODE state of a carry (default: the carry itself).

The lifecycle compiles one loop per (method and its options, model structure, right-hand side,
save-buffer length; the scene's numbers are an argument, `StringPendulum.bind`), runs it, stops on a failed step or guard with the status the `StepCode` names, and
assembles the `Trajectory`. The guards (integrators/README.md, "One guard policy"): after every
step the saved state is finite and below the blow-up bound, the deployed length inside its
range, and the step's own code (e.g. Newton failed, the LGVI's Cayley bound) is ok; the energy
balance is checked at saved points only. JAX is imported inside the functions that trace.
"""

from __future__ import annotations

import abc
import dataclasses
import time
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np

from reelbench.integrators import rhs as _rhs
from reelbench.integrators.base import (Capability, Integrator, Status, Trajectory, energy_reason, fixed_step_grid, last_step,
                              step_times)
from reelbench.integrators.lifecycle import (CompileCache, ODEProblem, Run, blowup_reason, bucket, length_reason,
                                   ode_trajectory, run_in_chunks, start_run, step_indices)

__all__ = ["FixedStepMethod", "StepCode", "StepFailure", "StepResult", "run_fixed_step"]


# ------------------------------------------------------------------------------------------
# What a step reports
# ------------------------------------------------------------------------------------------
class StepResult(NamedTuple):
    """What one step reports besides its new carry (like an item of diffrax's ``RESULTS``).

    ``code``: int32, a `StepCode` (0 = ok); ``iterations``: int32, the Newton / fixed-point
    iterations of this step (0 for an explicit step), summed into ``stats["newton_iterations"]``."""

    code: Any
    iterations: Any

    @classmethod
    def of(cls, code=0, iterations=0) -> "StepResult":
        """A result with int32 fields (traceable)."""
        from reelbench.models._jax import jnp

        return cls(jnp.asarray(code, jnp.int32), jnp.asarray(iterations, jnp.int32))


@dataclass(frozen=True)
class StepFailure:
    """What a nonzero `StepCode` means: the run's status and the reason in words."""

    code: int
    name: str
    status: Status
    words: str


class StepCode:
    """The one table of step result codes, shared by the lifecycle and every method.

    0 is ok. The lifecycle's own guards use `NON_FINITE`, `LENGTH_LIMIT` and `ENERGY`; a step
    may report `NEWTON_FAILED` or a code it defines with `define` (the LGVI's Cayley bound)."""

    OK = 0
    _table: ClassVar[dict[int, StepFailure]] = {}

    @classmethod
    def define(cls, name: str, status: Status, words: str) -> int:
        """The code of failure ``name`` (defined on first use; the same code for the same name)."""
        for failure in cls._table.values():
            if failure.name == name:
                if failure.status is not status:
                    raise ValueError(f"step code {name!r} is defined with status {failure.status.value!r}")
                return failure.code
        code = max(cls._table, default=0) + 1
        cls._table[code] = StepFailure(code, name, Status(status), words)
        return code

    @classmethod
    def failure(cls, code: int) -> StepFailure:
        if code not in cls._table:
            raise ValueError(f"unknown step code {code!r} (defined: {sorted(cls._table)})")
        return cls._table[code]


StepCode.NON_FINITE = StepCode.define("non_finite", Status.DIVERGED, "the new state is not finite or blew up")
StepCode.LENGTH_LIMIT = StepCode.define("length_limit", Status.LENGTH_LIMIT,
                                        "the deployed length left its range")
StepCode.ENERGY = StepCode.define("energy", Status.DIVERGED, "the energy balance error exceeded its bound")
StepCode.NEWTON_FAILED = StepCode.define("newton_failed", Status.NEWTON_FAILED,
                                         "the step's nonlinear solve did not converge")


class LoopState(NamedTuple):
    """The lifecycle's carry around the method's: the step count and what failed, if anything."""

    carry: Any
    k: Any  # steps taken
    code: Any  # StepCode of the step or guard that stopped the run (0: none)
    iterations: Any  # summed over the steps (the failed one included)
    max_iterations: Any
    fail_ell: Any  # deployed length of the failed step's state (a length_limit reason)
    fail_err: Any  # energy balance error at the saved point that failed the energy guard


# ------------------------------------------------------------------------------------------
# The contract
# ------------------------------------------------------------------------------------------
class FixedStepMethod(Integrator):
    """A fixed-step method in the fewest lines: subclass, set ``name`` / ``order`` /
    ``description``, write ``step``. The lifecycle (`run_fixed_step`) does the rest.

    Hooks with defaults for a method on the quaternion ODE state (a method that carries more,
    e.g. momenta, overrides them; the LGVI does): `initial_state`, `saved`, `coordinates`,
    `saved_energy_error`, `trajectory`, and for its options `option_defaults`,
    `check_options`, `run_parameters`, `failure_reason`, `loop_key`.
    """

    capabilities: ClassVar[frozenset[Capability]] = frozenset({Capability.FIXED_STEP})
    implementation: ClassVar[str] = "jax-compiled"
    #: right-hand-side evaluations per step, if the method has a fixed count: reported as
    #: ``stats["rhs_evals"]`` (the work axis of the work-precision plot); None: not counted
    evals_per_step: ClassVar[int | None] = None
    #: whether the step uses ``ode.f`` (then ``solve(rhs=...)`` selects it); False: the method
    #: has its own discrete equations and takes no ``rhs``
    uses_rhs: ClassVar[bool] = True
    #: what the results record as ``rhs`` for a method with its own equations (``uses_rhs`` False)
    rhs_label: ClassVar[str | None] = None
    #: the method's own solve() options with their defaults (checked by `check_options`,
    #: handed to the step as run-time values through `run_parameters`)
    option_defaults: ClassVar[dict[str, Any]] = {}

    def init(self, ode: ODEProblem, y0):
        return y0

    @abc.abstractmethod
    def step(self, ode: ODEProblem, carry, t, h):
        """One step of size ``h`` from time ``t``: the new carry, or (carry, `StepResult`)."""

    def state(self, ode: ODEProblem, carry):
        return carry

    # -- hooks -----------------------------------------------------------------------------
    def initial_state(self, run: Run, ode: ODEProblem):
        """What ``init`` starts from (numpy, outside the compiled loop): the ODE state y0."""
        return np.asarray(ode.model.initial_ode_state(), dtype=float)

    def saved(self, ode: ODEProblem, carry):
        """What the lifecycle saves and guards of a carry (an array or a tuple of arrays)."""
        return self.state(ode, carry)

    def coordinates(self, ode: ODEProblem, saved):
        """The generalized coordinates x of a saved state (the deployed-length guard's)."""
        return saved[ode.layout.y_x]

    def saved_energy_error(self, ode: ODEProblem, saved, E0):
        """|E − W − E0| of a saved state (the energy guard, at saved points)."""
        from reelbench.integrators.base import energy_error_ode

        return energy_error_ode(ode.model, saved, E0)

    def trajectory(self, run: Run, ode: ODEProblem, t: np.ndarray, saved, n: int) -> Trajectory:
        """The `Trajectory` of the first ``n`` saved states (numpy, buffers of the bucketed length)."""
        return ode_trajectory(run.model, run.scene, t, np.asarray(saved)[:n], status=Status.OK, reason="",
                              stats={}, integrator=self.name, settings={})

    def check_options(self, options: dict) -> dict:
        """The method's options (`option_defaults`) with the given ones, checked (ValueError)."""
        return {**self.option_defaults, **options}

    def run_parameters(self, options: dict) -> dict:
        """Run-time values of the compiled loop (``ode.params`` in the step), from the options."""
        return {}

    def failure_reason(self, run: Run, code: int, traj: Trajectory) -> str:
        """Words for a failed step's own code (`StepCode`), with this run's settings."""
        return StepCode.failure(code).words

    def loop_key(self):
        """What the compiled loop depends on besides the model, rhs and buffer: the class and the
        instance's configuration (its attributes), so two configurations never share a loop."""
        return type(self), tuple(sorted((k, _hashable(v)) for k, v in vars(self).items()))

    def solve(self, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None, max_steps=None,
              time_limit=None, rhs=None, **options) -> Trajectory:
        """Fixed step ``dt`` (tolerances do not apply and are refused). ``rhs``: the right-hand
        side ``ode.f`` ("closed_form", the default, or "autodiff"; a method that uses no
        ``ode.f`` takes none). ``options``: the method's own (`option_defaults`)."""
        return run_fixed_step(self, scene, t_end, dt=dt, rtol=rtol, atol=atol, save_every=save_every,
                              max_steps=max_steps, time_limit=time_limit, rhs=rhs, options=options)


def _hashable(value):
    try:
        hash(value)
        return value
    except TypeError:
        return repr(value)


# ------------------------------------------------------------------------------------------
# The compiled loop
# ------------------------------------------------------------------------------------------
_LOOPS = CompileCache(maxsize=32)


def _take_step(method, ode, carry, t, h):
    """(new carry, StepResult or None): either form of ``step``'s result."""
    out = method.step(ode, carry, t, h)
    if isinstance(out, tuple) and len(out) == 2 and isinstance(out[1], StepResult):
        return out
    return out, None


def _guard(method, ode, carry, result, blowup):
    """(StepCode, deployed length) of a new carry: the step's own code, else the state guards."""
    from reelbench.models._jax import jax, jnp

    model, lay = ode.model, ode.layout
    saved = method.saved(ode, carry)
    good = jnp.asarray(True)
    for a in jax.tree_util.tree_leaves(saved):
        # one reduction per array: NaN compares false and |±inf| = inf, so a non-finite state
        # fails as a blown-up one does (an all-reduce of the comparison: measured 3x faster on
        # XLA CPU than the max of |a| it replaces, same result)
        good = good & jnp.all(jnp.abs(a) < blowup)
    code = jnp.zeros((), jnp.int32) if result is None else jnp.asarray(result.code, jnp.int32)
    code = jnp.where((code == 0) & ~good, StepCode.NON_FINITE, code)
    ell = jnp.zeros((), jnp.float64)
    if lay.has_reel:
        x = method.coordinates(ode, saved)
        ell = model.L - model.reel_coordinate(x)
        code = jnp.where((code == 0) & ~(model.deployed_length_margin(x) > 0.0), StepCode.LENGTH_LIMIT, code)
    return code.astype(jnp.int32), ell


def _keep_saved_if_failed(method, ode, good, carry1, carry):
    """The carry after a step: ``carry1``, except that a failed step (``good`` false) keeps
    ``carry`` (the last good state, which the run ends with). Where ``saved`` returns leaves of
    the carry itself (the LGVI's x, R, p, W), only those are kept: the others (its ∇V and Newton
    history) are never read after a failure, and each select skipped saves a pass over the array
    every step (~1 µs per 2,000 numbers on XLA CPU). Where ``saved`` computes new arrays from
    the carry (RATTLE's ODE state), every leaf is kept."""
    from reelbench.models._jax import jax, jnp

    carry_ids = {id(a) for a in jax.tree_util.tree_leaves(carry1)}
    saved_ids = {id(a) for a in jax.tree_util.tree_leaves(method.saved(ode, carry1))}
    if not saved_ids <= carry_ids:
        saved_ids = carry_ids
    return jax.tree_util.tree_map(lambda a, b: jnp.where(good, a, b) if id(a) in saved_ids else a, carry1, carry)


def _steps_until(method, ode, h, k_last, h_last, blowup, seen: dict):
    """The inner loop: steps until a target step index or a failure; step ``k_last`` has size
    ``h_last`` (the one that lands on t_end), every other ``h`` (run-time values: a new step size
    compiles nothing). ``seen["result"]`` records (at trace time) whether the step returns a
    `StepResult`."""
    from reelbench.models._jax import jax, jnp

    def cond(c):
        s, target = c
        return (s.k < target) & (s.code == 0)

    def body(c):
        s, target = c
        carry1, result = _take_step(method, ode, s.carry, s.k * h, jnp.where(s.k == k_last, h_last, h))
        seen["result"] = result is not None
        code, ell = _guard(method, ode, carry1, result, blowup)
        it = jnp.zeros((), jnp.int32) if result is None else jnp.asarray(result.iterations, jnp.int32)
        good = code == 0
        carry = _keep_saved_if_failed(method, ode, good, carry1, s.carry)
        s = LoopState(carry, jnp.where(good, s.k + 1, s.k), code, s.iterations + it,
                      jnp.maximum(s.max_iterations, it), jnp.where(good, s.fail_ell, ell), s.fail_err)
        return s, target

    return lambda s, target: jax.lax.while_loop(cond, body, (s, target))[0]


def _fresh(method, ode, y0):
    """The lifecycle's state at the start of a run (explicit dtypes: no weak types in the loop)."""
    from reelbench.models._jax import jnp

    i0, f0 = jnp.zeros((), jnp.int32), jnp.zeros((), jnp.float64)
    return LoopState(method.init(ode, y0), i0, i0, i0, i0, f0, f0)


def _make_loop(method: FixedStepMethod, ode: ODEProblem, n_buf: int, seen: dict):
    """The run as one function of (the model's values, y0, state, j0, k_stop, h, k_last, h_last, save_idx, n_save, E0,
    bound, blowup, params): from saved slot j0 (0: a fresh start from y0) until every slot is saved, a step or
    guard fails, or step k_stop (the end of a chunk) is reached. Returns (state, the next slot,
    this call's saved buffers (step index, saved state): slot j at index j - j0).

    The slots are the save grid's; when a step fails, the last good state before it is kept as
    one more slot (off the grid unless it is on it), within the energy bound."""
    from reelbench.models._jax import jax, jnp

    def run(values, y0, state, j0, k_stop, h, k_last, h_last, save_idx, n_save, E0, e_bound, blowup, params):
        ode_t = ode.bind(values, params)  # the scene's numbers are arguments, not constants
        state = jax.lax.cond(j0 == 0, lambda s: _fresh(method, ode_t, y0), lambda s: s, state)
        steps = _steps_until(method, ode_t, h, k_last, h_last, blowup, seen)
        first = (state.k, method.saved(ode_t, state.carry))
        bufs = jax.tree_util.tree_map(lambda a: jnp.zeros((n_buf,) + a.shape, a.dtype).at[0].set(a), first)

        def outer_cond(c):
            s, j, _ = c
            return (j < n_save) & (s.code == 0) & (s.k < k_stop)

        def outer_body(c):
            s, j, bufs = c
            s = steps(s, jnp.minimum(save_idx[j], k_stop))
            saved = method.saved(ode_t, s.carry)
            err = method.saved_energy_error(ode_t, saved, E0)
            within = err <= e_bound
            reached = (s.code == 0) & (s.k == save_idx[j])
            over = reached & ~within  # the slot is written but not counted
            last_good = (s.code != 0) & (s.k > save_idx[j - 1]) & within  # a step failed after progress
            s = s._replace(code=jnp.where(over, StepCode.ENERGY, s.code).astype(jnp.int32),
                           fail_err=jnp.where(over, err, s.fail_err))
            bufs = jax.tree_util.tree_map(lambda b, a: b.at[j - j0].set(a), bufs, (s.k, saved))
            return s, jnp.where((reached & ~over) | last_good, j + 1, j), bufs

        j = jnp.where(j0 == 0, 1, j0).astype(jnp.int32)
        return jax.lax.while_loop(outer_cond, outer_body, (state, j, bufs))

    return run


@dataclass(frozen=True)
class _Loop:
    """A compiled loop, the zero state of its first call and whether its step counts iterations."""

    fn: Any
    zero_state: Any
    counts_iterations: bool


def _compile_loop(method, ode, n_buf, y0, params, rest) -> _Loop:
    """AOT-compile the loop for these argument shapes (``rest``: j0 .. blowup, numpy)."""
    from reelbench.models._jax import jax, jnp

    values = _rhs.device_values(ode.model)
    shape = jax.eval_shape(lambda v, y, p: _fresh(method, ode.bind(v, p), y), values, y0, params)
    # on the device once: a first call then passes no host arrays for the state it does not read
    zero = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shape)
    seen: dict = {}
    fn = jax.jit(_make_loop(method, ode, n_buf, seen)).lower(values, y0, zero, *rest, params).compile()
    return _Loop(fn, zero, bool(seen.get("result", False)))


# ------------------------------------------------------------------------------------------
# The lifecycle of a fixed-step run
# ------------------------------------------------------------------------------------------
@dataclass
class _Progress:
    """Where a (chunked) run is: the loop state, the next saved slot, the saved slots so far."""

    state: Any
    j: int = 0
    k: int = 0
    code: int = 0
    pieces: list = dataclasses.field(default_factory=list)
    timed_out: bool = False
    scalars: Any = None  # the final LoopState's counters on the host (carry dropped)


def _run_chunks(run: Run, loop: _Loop, values, y0, n_run: int, n_save: int, rest: tuple, params) -> _Progress:
    """Call the compiled loop until the run ends, in chunks when there is a time limit
    (`run_in_chunks`: the clock is read between chunks, never inside the compiled loop)."""
    from reelbench.models._jax import jax

    prog = _Progress(state=loop.zero_state)

    def advance(chunk: int) -> tuple[int, bool]:
        k_stop = min(n_run, prog.k + chunk)
        state, j, bufs = loop.fn(values, y0, prog.state, np.int32(prog.j), np.int32(k_stop), *rest, params)
        j, k, code = (int(v) for v in jax.device_get((j, state.k, state.code)))  # one transfer
        prog.pieces.append((bufs, j - prog.j))
        done = k - prog.k
        prog.state, prog.j, prog.k, prog.code = state, j, k, code
        return done, bool(code or j >= n_save)

    prog.timed_out = run_in_chunks(run, advance, n_run)
    return prog


def _device_get(tree):
    from reelbench.models._jax import jax

    return jax.device_get(tree)


def _saved_buffers(prog: _Progress, n_buf: int):
    """The saved slots of every chunk in one buffer of the bucketed length, and their count."""
    from reelbench.models._jax import jax

    if len(prog.pieces) == 1:
        bufs, n = prog.pieces[0]
        return jax.tree_util.tree_map(np.asarray, bufs), n
    n = sum(m for _, m in prog.pieces)

    def join(*leaves):
        out = np.zeros((n_buf,) + np.shape(leaves[0])[1:], np.asarray(leaves[0]).dtype)
        np.concatenate([np.asarray(a)[:m] for a, (_, m) in zip(leaves, prog.pieces)], out=out[:n])
        return out

    return jax.tree_util.tree_map(join, *[b for b, _ in prog.pieces]), n


def _where(k: int, dt: float, t_end: float) -> str:
    return f"step {k + 1} (t = {k * dt:.6g} s -> {min((k + 1) * dt, t_end):.6g} s)"


def _ending(method, run: Run, prog: _Progress, traj: Trajectory, truncated: bool, n_run: int):
    """(status, reason, extra stats) of a finished fixed-step run."""
    dt, k, code, state = run.dt, prog.k, prog.code, prog.scalars
    where = _where(k, dt, run.t_end)
    kept = f"; trajectory kept up to the saved point t = {traj.t[-1]:.6g} s"
    if code == StepCode.NON_FINITE:
        return Status.DIVERGED, blowup_reason(where, run.guards.blowup) + kept, {}
    if code == StepCode.LENGTH_LIMIT:
        reason = length_reason(run.model, float(state.fail_ell), f"in {where}") + kept
        return Status.LENGTH_LIMIT, reason, {"event_time": min((k + 1) * dt, run.t_end)}
    if code == StepCode.ENERGY:
        return Status.DIVERGED, energy_reason(float(state.fail_err), run.guards.energy_bound, min(k * dt, run.t_end), kept), {}
    if code:
        return StepCode.failure(code).status, f"{where}: {method.failure_reason(run, code, traj)}{kept}", {}
    if prog.timed_out:
        return Status.TIME_LIMIT, run.time_limit_reason(min(k * dt, run.t_end), kept), {}
    if truncated:
        return Status.MAX_STEPS, (f"stopped after max_steps = {run.max_steps} steps at t = {min(n_run * dt, run.t_end):.6g} s "
                                  f"(t_end = {run.t_end:g} s)"), {}
    return Status.OK, "", {}


def run_fixed_step(method: FixedStepMethod, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None,
                   max_steps=None, time_limit=None, rhs=None, options=None, guards=None) -> Trajectory:
    """The lifecycle of a fixed-step run: validate, build the model, compile the loop of
    ``method.step`` with its guards, run it (in chunks under a time limit), and assemble the
    `Trajectory` with status, reason, stats and timing. ``guards`` overrides the model's
    thresholds (tests, studies)."""
    started = time.perf_counter()
    options = dict(options or {})
    rhs = _method_rhs(method, rhs)
    checked = {}
    run = start_run(method, scene, t_end, dt=dt, rtol=rtol, atol=atol, save_every=save_every, max_steps=max_steps,
                    time_limit=time_limit, rhs=rhs, options=options,
                    allowed=tuple(method.option_defaults), started=started,
                    validate=lambda mode: checked.update(method.check_options(options)))
    run.options = checked  # with the defaults filled in
    guards = run.guards = guards or run.guards
    ode = run.ode_problem()
    idx, n_run, truncated = step_indices(run.t_end, run.dt, save_every, max_steps)
    y0 = method.initial_state(run, ode)
    n_buf = bucket(len(idx), _nbytes(y0))
    idx_buf = np.full(n_buf, idx[-1], dtype=np.int32)
    idx_buf[: len(idx)] = idx
    params = method.run_parameters(checked)
    n_grid, _ = fixed_step_grid(run.t_end, run.dt, save_every)
    rest = (np.float64(run.dt), np.int32(n_grid - 1), np.float64(last_step(run.t_end, run.dt, n_grid)), idx_buf, np.int32(len(idx)), np.float64(guards.E0),
            np.float64(guards.energy_bound), np.float64(guards.blowup))
    # one loop per model structure: this model's numbers are its run-time argument
    key = (method.loop_key(), _rhs.structure_of(run.model), rhs, n_buf)
    loop = run.compiled(_LOOPS, key, lambda: _compile_loop(method, ode, n_buf, y0, params,
                                                           (np.int32(0), np.int32(0)) + rest))
    prog = _run_chunks(run, loop, _rhs.device_values(run.model), y0, n_run, len(idx), rest, params)
    prog.scalars = _device_get(prog.state._replace(carry=None))  # the counters, in one transfer
    (K, saved), n = _saved_buffers(prog, n_buf)
    traj = method.trajectory(run, ode, step_times(K[:n], run.dt, run.t_end), saved, n)
    status, reason, extra = _ending(method, run, prog, traj, truncated, n_run)
    stats = {"steps": prog.k, "rhs": rhs or method.rhs_label, **extra}
    if method.evals_per_step is not None:
        stats["rhs_evals"] = int(method.evals_per_step) * prog.k
    if loop.counts_iterations:
        stats.update(newton_iterations=int(prog.scalars.iterations),
                     max_newton_iterations=int(prog.scalars.max_iterations))
    traj.status, traj.reason, traj.integrator = status.value, reason, method.name
    traj.stats.update(stats)
    traj.settings = run.settings(rhs=rhs or method.rhs_label, **checked)
    return run.finish(traj)


def _nbytes(state) -> int:
    """Bytes of a method's state (a pytree of arrays)."""
    from reelbench.models._jax import jax

    return sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(state))


def _method_rhs(method: FixedStepMethod, rhs):
    """The right-hand side the method's ``ode.f`` uses (None for a method with its own equations)."""
    if method.uses_rhs:
        return _rhs.DEFAULT_RHS if rhs is None else rhs
    if rhs is not None:
        raise ValueError(f"{method.name}: rhs = {rhs!r} does not apply (the method has its own discrete "
                         "equations; allowed: omit rhs)")
    return None
