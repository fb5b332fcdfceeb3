"""One run lifecycle, shared by every integrator (issue #14).

What every ``solve()`` must do apart from taking steps lives here, once:

* **validation** of the arguments, before any work (`resolve_scene`, `check_positive`,
  `check_tolerances`, `check_max_steps`, `check_options`, `check_fixed_step`);
* the **save grid** (`integrators.base.save_times`, `step_indices` for a fixed step);
* the **guards** (`Guards`): the energy balance bound (from the model's own energy scale,
  `StringPendulum.energy_scale`), the blow-up / non-finite state, the deployed-length limits.
  Their thresholds are run-time values (arguments of the compiled loops), not constants baked
  into compiled code;
* **status codes and reasons** (`Status`, `blowup_reason`, `length_reason`, `energy_reason`);
* **typed stats** (`RunStats`);
* **timing**: compile vs run (`integrators.base.stamp_wall_time`: the whole call minus compile);
* **Trajectory assembly** from quaternion ODE states (`ode_trajectory`).

And the small contract of a fixed-step method, `FixedStepMethod`: a plugin author writes how
one step is taken (``step``; optionally ``init`` / ``state`` when the method carries more than
the ODE state) and gets all of the above for free. See integrators/README.md.
"""

from __future__ import annotations

import abc
import functools
import time
from dataclasses import dataclass
from typing import Any, ClassVar, TypedDict

import numpy as np

from integrators import rhs as _rhs
from integrators.base import (Capability, Integrator, Status, Trajectory, build_model_timed, check_positive,
                              energy_reason, initial_energy, save_times, stamp_wall_time)

__all__ = [
    "BLOWUP", "FixedStepMethod", "Guards", "ODEProblem", "RunStats", "blowup_reason", "check_fixed_step",
    "check_max_steps", "check_options", "check_positive", "check_tolerances", "energy_reason", "length_reason",
    "ode_trajectory", "resolve_scene", "step_indices",
]

#: A state component beyond this magnitude counts as divergence (positions are tens of metres,
#: velocities at most hundreds of m/s in every shipped scene). The default of `Guards.blowup`.
BLOWUP = 1e8


# ------------------------------------------------------------------------------------------
# Validation (bad arguments raise ValueError before any work)
# ------------------------------------------------------------------------------------------
def resolve_scene(scene):
    """A `models.Scene` from a scene or a scene name."""
    from models import load_scene
    from models.scene import Scene

    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, str):
        return load_scene(scene)
    raise ValueError(f"scene = {scene!r} is invalid (allowed: a models.Scene or a scene name)")


def check_tolerances(rtol, atol) -> None:
    """rtol in (0, 1), atol > 0; both required."""
    if rtol is None:
        raise ValueError("rtol is required for an adaptive method (allowed: a finite number in (0, 1))")
    if atol is None:
        raise ValueError("atol is required for an adaptive method (allowed: a finite number > 0)")
    check_positive("rtol", rtol)
    if rtol >= 1:
        raise ValueError(f"rtol = {rtol!r} is invalid (allowed: a finite number in (0, 1))")
    check_positive("atol", atol)


def check_max_steps(max_steps) -> None:
    if max_steps is None:
        return
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps = {max_steps!r} is invalid (allowed: an integer >= 1, or None)")


def check_options(name: str, options: dict, allowed: tuple[str, ...] = ()) -> None:
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        allowed_txt = ", ".join(allowed) if allowed else "none"
        raise ValueError(f"{name}: unknown option(s) {', '.join(map(repr, unknown))} (allowed options: {allowed_txt})")


def check_fixed_step(t_end, dt, save_every, max_steps) -> None:
    """The arguments of a fixed-step run: t_end, dt > 0, dt <= t_end, optional save_every, max_steps."""
    check_positive("t_end", t_end)
    check_positive("dt", dt)
    check_positive("save_every", save_every, allow_none=True)
    if max_steps is not None and (isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer))
                                  or max_steps < 1):
        raise ValueError(f"max_steps = {max_steps!r} is invalid (allowed: an integer >= 1)")
    if dt > t_end:
        raise ValueError(f"dt = {dt!r} is larger than t_end = {t_end!r}")


def step_indices(t_end, dt, save_every, max_steps):
    """Step indices to save (0 first, the last step run last) and the number of steps run."""
    n = int(np.floor(t_end / dt + 1e-9))
    idx = np.rint(save_times(t_end, save_every, dt) / dt).astype(np.int64)
    truncated = max_steps is not None and n > max_steps
    n_run = min(n, max_steps) if max_steps is not None else n
    idx = idx[idx <= n_run]
    if idx[-1] != n_run:
        idx = np.append(idx, n_run)
    return idx, n_run, truncated


def bucket(n: int) -> int:
    """Save-buffer length: the next power of two (at least 256), so that runs of other lengths
    share compiled code."""
    return max(256, 1 << (int(n) - 1).bit_length())


# ------------------------------------------------------------------------------------------
# Guards and reasons
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Guards:
    """The run-time thresholds every method stops by (issue #7), asked of the model.

    ``E0``: the energy of the initial state; ``energy_bound``: the largest |E − W − E0| (J)
    before a run is ``diverged`` (`integrators.base.energy_bound`: ENERGY_GROWTH_FACTOR × the
    model's `energy_scale`); ``blowup``: a state component at least this large is ``diverged``.
    The deployed-length limits are the model's (`deployed_length_margin`).
    """

    E0: float
    energy_bound: float
    blowup: float = BLOWUP

    @classmethod
    def for_model(cls, model) -> "Guards":
        """The model's guards (computed once per model, then cached)."""
        return _model_guards(model)


def guards_timed(model) -> tuple[Guards, float]:
    """(the model's `Guards`, seconds spent computing them): 0.0 when cached. Computing them runs
    eager JAX once per model (setup): the adapters book it with ``compile_time``, like
    `integrators.base.build_model_timed`."""
    misses = _model_guards.cache_info().misses
    t0 = time.perf_counter()
    guards = _model_guards(model)
    return guards, (time.perf_counter() - t0 if _model_guards.cache_info().misses > misses else 0.0)


@functools.lru_cache(maxsize=64)
def _model_guards(model) -> Guards:
    from integrators.base import energy_bound

    return Guards(E0=initial_energy(model), energy_bound=energy_bound(model))


def finite_prefix(y: np.ndarray, blowup: float = BLOWUP) -> int:
    """Number of leading rows of y that are finite and below ``blowup`` in magnitude."""
    good = np.all(np.isfinite(y), axis=1) & np.all(np.abs(np.nan_to_num(y, nan=np.inf)) < blowup, axis=1)
    bad = np.flatnonzero(~good)
    return int(bad[0]) if bad.size else len(y)


def state_ok(y: np.ndarray, blowup: float = BLOWUP) -> bool:
    """One state is finite and below ``blowup`` in magnitude (the blow-up guard, in numpy)."""
    return bool(np.all(np.isfinite(y)) and np.max(np.abs(y)) < blowup)


@functools.lru_cache(maxsize=64)
def energy_guard(model):
    """(error, bound): ``error(y)`` = |E − W − E0| of an ODE state (float, jitted), and the bound
    of `integrators.base.energy_bound` beyond which the run is ``diverged`` (the model's `Guards`).
    The adapters check it on the states they save."""
    from integrators.base import energy_error_ode
    from models._jax import jax

    guards = Guards.for_model(model)
    f = jax.jit(lambda y: energy_error_ode(model, y, guards.E0))
    return (lambda y: float(f(y))), guards.energy_bound


def blowup_reason(where: str, blowup: float = BLOWUP) -> str:
    """The `reason` of a run stopped by a non-finite or blown-up state; ``where`` says when."""
    return f"non-finite or blown-up state (|y| >= {blowup:g}) in {where}"


def length_reason(model, ell: float, where: str) -> str:
    """The `reason` of a run stopped on the deployed-length limits (wording: the model's)."""
    return f"the deployed length reached {model.length_limit_name(ell)} {where}"


class RunStats(TypedDict, total=False):
    """The fields of `Trajectory.stats` (integrators/README.md says which method reports which)."""

    steps: int
    rejected_steps: int
    attempted_steps: int
    rhs_evals: int
    jac_evals: int
    lu_decompositions: int
    newton_iterations: int
    max_newton_iterations: int
    min_step: float
    median_step: float
    max_step: float
    time_per_step: float
    wall_time: float
    compile_time: float
    event_time: float
    rhs: str


def ode_trajectory(model, scene, t, y, *, status, reason, stats, integrator, settings) -> Trajectory:
    """A `Trajectory` from quaternion ODE states y (n, ny) saved at times t (`models.layout`)."""
    lay = model.layout
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float).reshape(len(t), lay.ny)
    return Trajectory(
        t=t,
        x=y[:, lay.y_x].copy(),
        attitude=y[:, lay.y_quat].copy() if lay.has_attitude else None,
        attitude_kind="quaternion",
        velocity=y[:, lay.y_w].copy(),
        work=y[:, lay.y_work][:, 0].copy() if lay.has_work else np.zeros(len(t)),
        status=str(status.value if isinstance(status, Status) else status),
        reason=reason,
        stats=dict(stats),
        integrator=integrator,
        settings=settings,
        scene_name=scene.name,
    )


# ------------------------------------------------------------------------------------------
# The fixed-step contract
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ODEProblem:
    """What a step sees: ``f(t, y)`` the right-hand side on the quaternion ODE state
    y = (x, quat, w, W) (closed form by default, `integrators.rhs`), its ``layout``
    (`models.layout.StateLayout`: slices ``y_x``, ``y_quat``, ``y_w``, ``y_work``) and the ``model``
    (`models.StringPendulum`) for anything else (energy, forces, mass matrix)."""

    model: Any
    f: Any
    layout: Any


_CODES = {1: Status.DIVERGED, 2: Status.LENGTH_LIMIT, 3: Status.DIVERGED}  # blow-up, length, energy
_COMPILED: dict = {}


class FixedStepMethod(Integrator):
    """A fixed-step method in the fewest lines: subclass, set ``name`` / ``order`` /
    ``description``, write ``step``. The lifecycle (`run_fixed_step`) does the rest.

    * ``init(ode, y0) -> carry``: the method's state from the initial ODE state (default: y0);
    * ``step(ode, carry, t, h) -> carry``: one step of size h from time t (traced by JAX:
      use ``jax.numpy``, no Python branches on values);
    * ``state(ode, carry) -> y``: the ODE state of a carry (default: the carry itself).

    ``ode`` is an `ODEProblem`. After every step the lifecycle checks the state (finite and
    below the blow-up bound, deployed length inside its range, energy balance within the
    bound) and stops with ``diverged`` / ``length_limit``, keeping the saved points before.
    """

    capabilities: ClassVar[frozenset[Capability]] = frozenset({Capability.FIXED_STEP})
    #: right-hand-side evaluations per step, if the method has a fixed count: reported as
    #: ``stats["rhs_evals"]`` (the work axis of the work-precision plot); None: not counted
    evals_per_step: ClassVar[int | None] = None

    def init(self, ode: ODEProblem, y0):
        return y0

    @abc.abstractmethod
    def step(self, ode: ODEProblem, carry, t, h):
        """One step of size ``h`` from time ``t``; returns the new carry."""

    def state(self, ode: ODEProblem, carry):
        return carry

    def solve(self, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None, max_steps=None,
              rhs=_rhs.DEFAULT_RHS, **options) -> Trajectory:
        """Fixed step ``dt``; ``rtol``/``atol`` do not apply and are ignored. ``rhs``: the
        right-hand side ``ode.f`` ("closed_form" or "autodiff")."""
        return run_fixed_step(self, scene, t_end, dt=dt, save_every=save_every, max_steps=max_steps, rhs=rhs,
                              **options)


def _make_loop(method: FixedStepMethod, ode: ODEProblem):
    """The whole run as one function of (y0, h, save_idx, n_save, E0, energy_bound, blowup)."""
    from integrators.base import energy_error_ode
    from models._jax import jax, jnp

    model, lay = ode.model, ode.layout

    def check(y, E0, e_bound, blowup):
        code = jnp.where(~(jnp.all(jnp.isfinite(y)) & (jnp.max(jnp.abs(y)) < blowup)), 1, 0)
        if lay.has_reel:
            code = jnp.where((code == 0) & ~(model.deployed_length_margin(y[lay.y_x]) > 0.0), 2, code)
        err = energy_error_ode(model, y, E0)
        code = jnp.where((code == 0) & ~(err <= e_bound), 3, code)
        return code.astype(jnp.int32), err

    def run(y0, h, save_idx, n_save, E0, e_bound, blowup):
        n_buf = save_idx.shape[0]
        Y = jnp.zeros((n_buf, lay.ny)).at[0].set(y0)
        K = jnp.zeros(n_buf, jnp.int32)
        i0 = jnp.asarray(0, jnp.int32)
        # (carry, k, code, failing state, its energy error)
        s0 = (method.init(ode, y0), i0, i0, jnp.asarray(y0), jnp.asarray(0.0))

        def inner_cond(c_):
            (_, k, code, _, _), target = c_
            return (k < target) & (code == 0)

        def inner_body(c_):
            (carry, k, _, _, _), target = c_
            carry1 = method.step(ode, carry, k * h, h)
            y1 = method.state(ode, carry1)
            code, err = check(y1, E0, e_bound, blowup)
            good = code == 0
            carry = jax.tree_util.tree_map(lambda a, b: jnp.where(good, a, b), carry1, carry)
            return (carry, jnp.where(good, k + 1, k), code, y1, err), target

        def outer_cond(c_):
            s, j, _, _ = c_
            return (j < n_save) & (s[2] == 0)

        def outer_body(c_):
            s, j, Y, K = c_
            s, _ = jax.lax.while_loop(inner_cond, inner_body, (s, save_idx[j]))
            ok = s[2] == 0  # a failed step is not saved: the run keeps the saved points before it
            Y = jnp.where(ok, Y.at[j].set(method.state(ode, s[0])), Y)
            K = jnp.where(ok, K.at[j].set(s[1]), K)
            return s, jnp.where(ok, j + 1, j), Y, K

        s, j, Y, K = jax.lax.while_loop(outer_cond, outer_body, (s0, jnp.asarray(1, jnp.int32), Y, K))
        _, k, code, y_fail, err = s
        return Y, K, j, k, code, y_fail, err

    return run


def _compiled_loop(method, ode, n_buf, rhs, example_args):
    """(AOT-compiled loop, compile seconds; 0 when cached) per (method class, model, rhs, buffer)."""
    from models._jax import jax

    key = (type(method), ode.model, rhs, n_buf)
    hit = _COMPILED.get(key)
    if hit is not None:
        return hit, 0.0
    t0 = time.perf_counter()
    compiled = jax.jit(_make_loop(method, ode)).lower(*example_args).compile()
    _COMPILED[key] = compiled
    return compiled, time.perf_counter() - t0


def run_fixed_step(method: FixedStepMethod, scene, t_end=None, *, dt=None, save_every=None, max_steps=None,
                   rhs=_rhs.DEFAULT_RHS, guards: Guards | None = None, **options) -> Trajectory:
    """The lifecycle of a fixed-step run: validate, build the model, compile the loop of
    ``method.step`` with its guards, run, and assemble the `Trajectory` with status, reason,
    stats and timing. ``guards`` overrides the model's thresholds (tests, studies)."""
    started = time.perf_counter()  # run time = the whole call minus compilation (issue #11)
    check_options(method.name, options)
    _rhs.check_rhs(rhs)
    scene = resolve_scene(scene)
    t_end = scene.t_end if t_end is None else t_end
    check_fixed_step(t_end, dt, save_every, max_steps)
    t_end, dt = float(t_end), float(dt)

    model, setup_time = build_model_timed(scene)
    lay = model.layout
    ode = ODEProblem(model=model, f=_rhs.ode_rhs(model, rhs), layout=lay)
    model_guards, guards_time = guards_timed(model)  # setup, booked as compile time
    guards = guards or model_guards
    setup_time += guards_time
    idx, n_run, truncated = step_indices(t_end, dt, save_every, max_steps)
    n_buf = bucket(len(idx))
    idx_buf = np.full(n_buf, idx[-1], dtype=np.int32)
    idx_buf[: len(idx)] = idx
    y0 = np.asarray(model.initial_ode_state(), dtype=float)
    args = (y0, np.float64(dt), idx_buf, np.int32(len(idx)), np.float64(guards.E0), np.float64(guards.energy_bound),
            np.float64(guards.blowup))
    compiled, compile_time = _compiled_loop(method, ode, n_buf, rhs, args)

    Y, K, j, k, code, y_fail, err = compiled(*args)
    Y, K, y_fail = np.asarray(Y), np.asarray(K), np.asarray(y_fail)
    n, k, code, err = int(j), int(k), int(code), float(err)
    stats: RunStats = {"steps": k, "compile_time": compile_time + setup_time, "rhs": rhs}
    if method.evals_per_step is not None:
        stats["rhs_evals"] = int(method.evals_per_step) * k
    status, reason = Status.OK, ""
    if code:
        status = _CODES[code]
        where = f"step {k + 1} (t = {k * dt:.6g} s -> {(k + 1) * dt:.6g} s)"
        kept = f"; trajectory kept up to the saved point t = {K[n - 1] * dt:.6g} s"
        if code == 1:
            reason = blowup_reason(where, guards.blowup) + kept
        elif code == 2:
            reason = length_reason(model, float(model.L - y_fail[lay.y_x][0]), f"in {where}") + kept
            stats["event_time"] = (k + 1) * dt
        else:
            reason = energy_reason(err, guards.energy_bound, (k + 1) * dt, kept)
    elif truncated:
        status = Status.MAX_STEPS
        reason = f"stopped after max_steps = {max_steps} steps at t = {n_run * dt:.6g} s (t_end = {t_end:g} s)"
    settings = {"dt": dt, "t_end": t_end, "save_every": save_every, "max_steps": max_steps, "rhs": rhs}
    traj = ode_trajectory(model, scene, K[:n] * dt, Y[:n], status=status, reason=reason, stats=stats,
                          integrator=method.name, settings=settings)
    stamp_wall_time(traj, started)
    traj.stats["time_per_step"] = traj.stats["wall_time"] / max(k, 1)
    return traj


def clear_cache() -> None:
    """Forget the compiled fixed-step loops (tests, memory)."""
    _COMPILED.clear()
