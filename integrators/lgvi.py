"""Lie group variational integrator (Lee, Leok & McClamroch 2011; MODEL.md §6).

Discrete state (s_p, q, R ∈ SO(3) as a matrix, discrete momenta p = (p_s, p_q, Π)). Each
step solves the implicit p_k equations for X = (Δs, Δq, c), F = cay(c), R_{k+1} = R_k F,
then evaluates p_{k+1} explicitly. The closed-form equations and the structured solver
(tridiagonal string rows + ≤4-unknown Newton in (Δs, c)) live in `integrators._lgvi_core`;
this module is the time loop: one jitted ``lax.while_loop`` over save slots with an inner
``while_loop`` over steps, compiled ahead of time (compile time measured apart from run
time), stopping cleanly with a `Status` when Newton fails, the state stops being finite, the
deployed length leaves (ℓ_min, L − b), a step's Cayley parameter exceeds `CAYLEY_BOUND` or (at
save points) the energy balance error exceeds `integrators.base.energy_bound`; the thresholds are
run-time arguments of the compiled loop (`integrators.lifecycle.Guards`).

The same loop runs the symmetric LGVI of MODEL.md §9 and its compositions
(`integrators.lgvi_sym`): a `Scheme` selects the discrete Lagrangian
(`DiscreteLagrangian(symmetric=...)`) and the substep coefficients γ_i; the guards, statuses and
the structured solver are shared. With the symmetric scheme and string forces (axial damping)
the midpoint string force is found by a fixed point around the structured solve (see
`DiscreteLagrangian.with_forcing`): it costs more Newton iterations per step (measured N = 4,
c = 0.5 N s: 5.3 vs 1.0 per step at fixed length, 9.2 vs 2.5 on retrieval, at h = 4 ms).

Forcing (MODEL.md §6): (h/2) Q_k at both ends of the step, Q_k = Q_u(t_k) + Q_c(s_k, Δs/h,
q_{k,2}); the work of step k is Q_k Δs and is accumulated in ``Trajectory.work``. The string
forces (axial damping) are explicit (Heun: (h/2) Q at g_k from w_k = M⁻¹ p_k, (h/2) Q at
g_{k+1} from the predicted velocity 2Δx/h − ẋ_k), see `integrators._lgvi_core`; their work
½ (Q⁻ + Q⁺)·Δx is added to W.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from integrators._lgvi_core import DiscreteLagrangian, cayley, small_solve
from integrators.base import (Capability, Integrator, Status, Trajectory, check_positive, energy_error,
                              energy_reason, stamp_wall_time, build_model_timed)
from integrators.lifecycle import bucket, check_fixed_step, guards_timed, resolve_scene, step_indices
from integrators.rhs import closed_form_of
from integrators.registry import register
from models._jax import jax, jnp

#: re-assemble the chord-Newton Jacobian when |dz| shrinks by less than this factor
CHORD_REFRESH = 0.1
#: Status codes of the jitted loop: 4 = energy guard (at a save point), 5 = Cayley guard.
_CODES = {1: Status.NEWTON_FAILED, 2: Status.DIVERGED, 3: Status.LENGTH_LIMIT, 4: Status.DIVERGED, 5: Status.DIVERGED}

#: Cayley guard (issue #7): a step whose Cayley parameter has |c| = tan(θ/2) > CAYLEY_BOUND, i.e.
#: rotates the body by θ > 90° in one step, does not resolve the rotation: the run stops there
#: (status "diverged", reason naming the Cayley parameter) instead of going on with a step that
#: Newton may have solved on the wrong branch (|c| → ∞ is a half-turn).
CAYLEY_BOUND = 1.0
_COMPILED: dict = {}
_VELOCITY: dict = {}
_MASS: dict = {}


@dataclass(frozen=True)
class Scheme:
    """Which LGVI: the discrete Lagrangian (§6 or the symmetric §9) and the composition.

    ``gammas``: substep fractions γ_i of a composition Φ_{γ_m h} ∘ … ∘ Φ_{γ_1 h} of the
    (symmetric) step (Σ γ_i = 1), or None for one step per step.
    """

    symmetric: bool = False
    gammas: tuple | None = None

    @property
    def substeps(self) -> int:
        """Symmetric steps per step (the work of one step is this many LGVI steps)."""
        return len(self.gammas) if self.gammas else 1


SECTION6 = Scheme()


def _make_run(model, scheme: Scheme = SECTION6):
    """The whole run as one function of (x0, R0, p0, h, save_idx, n_save, tol, maxit, e_bound, cayley_bound).

    ``e_bound`` (the energy guard, `integrators.lifecycle.Guards`) and ``cayley_bound`` (the Cayley
    guard) are run-time arguments, not constants of the compiled loop.

    ``save_idx`` is padded to a bucketed length so that runs of other lengths reuse the
    compiled code; only its first ``n_save`` entries are used.
    """
    dl = DiscreteLagrangian(model, symmetric=scheme.symmetric)
    lay = model.layout
    nz = dl.nz
    # the symmetric scheme's midpoint string force depends on the step: fixed point around the
    # structured solve (`DiscreteLagrangian.with_forcing`)
    lagged = dl.symmetric and dl.node_forced

    def energy_err(x, R, p, W, E0):
        return energy_error(model, x, R, dl.legendre(x, R, p), W, E0)

    def solve_x(ctx, p, h, z0, uv, tol, maxit):
        """(Δs, c, F, Δq, iterations, ok, z) of the p_k equations for the forcing in ``ctx``."""
        ps, pq, Pi = dl.split_momentum(p)
        if nz == 0:
            dq = uv[0]
            return (jnp.asarray(0.0), jnp.zeros(3), jnp.eye(3), dq, jnp.asarray(1, jnp.int32),
                    jnp.all(jnp.isfinite(dq)), z0)
        # With a reel, chord-Newton: the exact reduced Jacobian is assembled on the first
        # iteration and kept while the iteration contracts fast; later iterations only
        # evaluate the residual (about a quarter of the cost: J needs a tangent Thomas
        # pass). A slow contraction (ratio > CHORD_REFRESH) re-assembles J, so hard steps
        # still get full Newton. Without a reel J is cheap: plain Newton.
        def cond(c_):
            _, _, _, it_, conv, bad, _ = c_
            return (~conv) & (~bad) & (it_ < maxit)

        def body(c_):
            zz, J, dz_prev, it_, _, _, refresh = c_

            def exact(zz_):
                r_, J_, _ = dl.reduced_system(ctx, p, h, zz_, uv)
                return r_, J_

            def chord(zz_):
                return dl.reduced_residual(ctx, p, h, zz_, uv)[0], J

            r, J = jax.lax.cond(refresh, exact, chord, zz) if dl.reel else exact(zz)
            dz = -small_solve(J, r)
            zn = zz + dz
            bad = ~jnp.all(jnp.isfinite(zn))
            size = jnp.max(jnp.abs(dz))
            conv = size <= tol
            refresh = size > CHORD_REFRESH * dz_prev
            return jnp.where(bad, zz, zn), J, size, it_ + 1, conv, bad, refresh

        z_sol, _, _, it, conv, bad, _ = jax.lax.while_loop(
            cond, body, (z0, jnp.zeros((nz, nz)), jnp.asarray(jnp.inf), jnp.asarray(0, jnp.int32),
                         jnp.asarray(False), jnp.asarray(False), jnp.asarray(True)))
        ds, c = dl.unpack_z(z_sol)
        F = cayley(c) if dl.rigid else jnp.eye(3)
        u, v = dl.string_solve(ctx, pq, h, ds) if dl.reel else uv
        dq = u - v[:, None] * dl.body_term(ctx, F)[None, :]
        return ds, c, F, dq, it, conv & ~bad & jnp.all(jnp.isfinite(dq)), z_sol

    def step(x, R, p, gV, z, t, h, tol, maxit, cayley_bound):
        ctx = dl.context(t, x, R, gV, p)
        _, pq, _ = dl.split_momentum(p)
        uv = None if dl.reel else dl.string_solve(ctx, pq, h, jnp.asarray(0.0))
        # the first guess extrapolates the last two steps' solutions (z holds both), which
        # saves one iteration per step
        z0 = 2.0 * z[1] - z[0] if nz else z[1]
        ds, c, F, dq, it, newton_ok, z_sol = solve_x(ctx, p, h, z0, uv, tol, maxit)
        if lagged:
            # first pass: §6's explicit force at g_k (`context`); then the midpoint force of the
            # last iterate until Δx stops changing (contraction ≈ h γ_max / 2, see with_forcing)
            def fp_cond(c_):
                *_, n, conv, ok_ = c_
                return (~conv) & ok_ & (n < maxit)

            def fp_body(c_):
                ds_, c_prev, F_, dq_, it_, zz, n, _, _ = c_
                ctx_ = dl.with_forcing(ctx, h, ds_, dq_)
                uv_ = None if dl.reel else dl.string_solve(ctx_, pq, h, jnp.asarray(0.0))
                ds1, c1, F1, dq1, it1, ok1, z1 = solve_x(ctx_, p, h, zz, uv_, tol, maxit)
                conv = (jnp.max(jnp.abs(dq1 - dq_)) <= tol) & (jnp.abs(ds1 - ds_) <= tol)
                return ds1, c1, F1, dq1, it_ + it1, z1, n + 1, conv, ok1

            ds, c, F, dq, it, z_sol, _, conv, ok = jax.lax.while_loop(
                fp_cond, fp_body, (ds, c, F, dq, it, z_sol, jnp.asarray(0, jnp.int32), jnp.asarray(False), newton_ok))
            newton_ok = conv & ok
            ctx = dl.with_forcing(ctx, h, ds, dq)
        z_new = jnp.stack([z[1], z_sol])
        dx = jnp.concatenate([jnp.atleast_1d(ds), dq.ravel()]) if dl.reel else dq.ravel()
        x1 = x + dx
        R1 = R @ F if dl.rigid else R
        gV1 = model.potential_gradient(x1, R1)
        p1 = dl.hp_k1(ctx, h, ds, dq, c, gV1) / h
        dW = dl.work(ctx, h, ds, dq)
        finite = jnp.all(jnp.isfinite(x1)) & jnp.all(jnp.isfinite(p1)) & jnp.all(jnp.isfinite(R1)) & jnp.isfinite(dW)
        inside = model.deployed_length_margin(x1) > 0
        code = jnp.where(~newton_ok, 1, jnp.where(~finite, 2, jnp.where(~inside, 3, 0))).astype(jnp.int32)
        if dl.rigid:  # -- Cayley guard (issue #7): |c| > CAYLEY_BOUND ends the run (code 5) --
            code = jnp.where(((code == 0) | (code == 2)) & (c @ c > cayley_bound ** 2), 5, code).astype(jnp.int32)
        return (x1, R1, p1, gV1, dW, z_new), it, code

    if scheme.gammas is None:
        def macro_step(x, R, p, gV, z, k, h, tol, maxit, cayley_bound):
            return step(x, R, p, gV, z, k * h, h, tol, maxit, cayley_bound)

        z_shape = (2, nz)
    else:
        # composition: substep i of size γ_i h starts at t_k + (γ_1 + … + γ_{i−1}) h; each substep
        # keeps its own Newton history (z[i]: its last two solutions), since the sizes differ.
        # A failed substep's successors still run (scan), but the macro step is then rejected.
        gam = jnp.asarray(scheme.gammas)
        tau = jnp.asarray(np.concatenate([[0.0], np.cumsum(scheme.gammas)[:-1]]))

        def macro_step(x, R, p, gV, z, k, h, tol, maxit, cayley_bound):
            def sub(carry, inp):
                x_, R_, p_, gV_, W_, it_, code_ = carry
                g, tt, zi = inp
                (x1, R1, p1, gV1, dW, z1), it1, code1 = step(x_, R_, p_, gV_, zi, (k + tt) * h, g * h, tol, maxit, cayley_bound)
                code1 = jnp.where(code_ == 0, code1, code_)
                return (x1, R1, p1, gV1, W_ + dW, it_ + it1, code1), z1

            init = (x, R, p, gV, jnp.asarray(0.0), jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32))
            (x1, R1, p1, gV1, dW, it, code), z1 = jax.lax.scan(sub, init, (gam, tau, z))
            return (x1, R1, p1, gV1, dW, z1), it, code

        z_shape = (len(scheme.gammas), 2, nz)

    def run(x0, R0, p0, h, save_idx, n_save, tol, maxit, e_bound, cayley_bound):
        n_buf = save_idx.shape[0]
        gV0 = model.potential_gradient(x0, R0)
        E0 = model.energy(x0, R0, dl.legendre(x0, R0, p0))
        z0 = jnp.zeros(z_shape)  # reduced unknowns of the last two steps (Newton's first guess)
        bufs = (jnp.zeros((n_buf, lay.nx)).at[0].set(x0), jnp.zeros((n_buf, 3, 3)).at[0].set(R0),
                jnp.zeros((n_buf, lay.nw)).at[0].set(p0), jnp.zeros(n_buf), jnp.zeros(n_buf, jnp.int32))
        i0 = jnp.asarray(0, jnp.int32)
        # state: x, R, p, gV, W, z, k
        state0 = (x0, R0, p0, gV0, jnp.asarray(0.0), z0, i0)
        # stats: total iterations, max iterations, code, failing step
        stats0 = (i0, i0, i0, i0)

        def inner_cond(c_):
            state, stats, target = c_
            return (state[6] < target) & (stats[2] == 0)

        def inner_body(c_):
            state, stats, target = c_
            x, R, p, gV, W, z, k = state
            (x1, R1, p1, gV1, dW, z1), it, code = macro_step(x, R, p, gV, z, k, h, tol, maxit, cayley_bound)
            good = code == 0
            sel = lambda a, b: jnp.where(good, a, b)  # noqa: E731
            new_state = (sel(x1, x), sel(R1, R), sel(p1, p), sel(gV1, gV), sel(W + dW, W), sel(z1, z),
                         jnp.where(good, k + 1, k))
            tot, mx, _, fk = stats
            new_stats = (tot + it, jnp.maximum(mx, it), code, jnp.where(good, fk, k))
            return new_state, new_stats, target

        def outer_cond(c_):
            _, stats, j, _ = c_
            return (j < n_save) & (stats[2] == 0)

        def outer_body(c_):
            state, stats, j, bufs = c_
            state, stats, _ = jax.lax.while_loop(inner_cond, inner_body, (state, stats, save_idx[j]))
            x, R, p, _, W, _, k = state
            X, Rs, P, Ws, K = bufs
            bufs = (X.at[j].set(x), Rs.at[j].set(R), P.at[j].set(p), Ws.at[j].set(W), K.at[j].set(k))
            # energy guard (issue #7), at save points: beyond the bound (or NaN) -> code 4, and the
            # slot just written is not counted (the run keeps the previous save point)
            blown = (stats[2] == 0) & ~(energy_err(x, R, p, W, E0) <= e_bound)
            tot, mx, code, fk = stats
            stats = (tot, mx, jnp.where(blown, 4, code).astype(jnp.int32), jnp.where(blown, k, fk))
            return state, stats, jnp.where(blown, j, j + 1), bufs

        state, stats, j, bufs = jax.lax.while_loop(outer_cond, outer_body, (state0, stats0, jnp.asarray(1, jnp.int32), bufs))
        return bufs, j, stats

    return run


def _compiled_run(model, n_buf, example_args, scheme: Scheme = SECTION6):
    """AOT-compiled run for (model, buffer length, scheme); returns (compiled, compile_seconds)."""
    key = (id(model), n_buf, scheme)
    hit = _COMPILED.get(key)
    if hit is not None and hit[0] is model:
        return hit[1], 0.0
    t0 = time.perf_counter()
    compiled = jax.jit(_make_run(model, scheme)).lower(*example_args).compile()
    dt = time.perf_counter() - t0
    _COMPILED[key] = (model, compiled)
    return compiled, dt


def _mass_matrix_fn(model):
    """Jitted p = M(x, R) w by the O(N) closed form (the initial momentum)."""
    hit = _MASS.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    fn = jax.jit(closed_form_of(model).momentum)
    _MASS[id(model)] = (model, fn)
    return fn


def _velocity_fn(model, n_buf, example_args):
    """(w = M⁻¹ p over a whole save buffer, compile seconds; 0 when cached): the O(N) closed-form
    Legendre map (`ClosedFormEOM.velocity_from_momentum`) vmapped over the buffers, compiled ahead
    for their fixed (bucketed) length so that the run time contains its cost but not its
    compilation (issue #11: the dense autodiff map cost 0.25 s on a 0.5 s run at N = 80)."""
    key = (id(model), n_buf)
    hit = _VELOCITY.get(key)
    if hit is not None and hit[0] is model:
        return hit[1], 0.0
    t0 = time.perf_counter()
    fn = jax.jit(jax.vmap(closed_form_of(model).velocity_from_momentum)).lower(*example_args).compile()
    dt = time.perf_counter() - t0
    _VELOCITY[key] = (model, fn)
    return fn, dt


@register
class LGVI(Integrator):
    name = "lgvi"
    capabilities = frozenset({Capability.FIXED_STEP, Capability.IMPLICIT, Capability.VARIATIONAL,
                              Capability.GROUP_PRESERVING})
    order = 2
    #: measured (tests/test_orders.py): second order at fixed length, first while the length changes
    orders = {"fixed_length": 2, "reel": 1}
    description = "Lie group variational integrator (Lee-Leok-McClamroch 2011): Cayley SO(3), structured Newton"
    horizon_settings = {"dt": 0.005}
    #: the paper's figures: inside its stability limit (h ω_max < 2) on all three paper scenes at
    #: N = 10 (deployment's short elements diverge at 5 ms, measured)
    paper_settings = {"dt": 0.0025}
    cost_hint = (30.0, 0.3)
    #: the discrete Lagrangian and composition (subclasses: integrators.lgvi_sym)
    scheme: ClassVar[Scheme] = SECTION6

    def solve(self, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None, max_steps=None,
              newton_tol=1e-12, newton_max_iter=20, **options) -> Trajectory:
        """Integrate with fixed step ``dt``. ``rtol``/``atol`` do not apply (fixed step) and are ignored.

        Options: ``newton_tol`` (max |Newton update| of the reduced unknowns (Δs [m], c) to
        stop, default 1e-12), ``newton_max_iter`` (default 20).
        """
        started = time.perf_counter()  # run time = the whole call minus compilation (issue #11)
        if options:
            raise ValueError(f"{self.name}: unknown option(s) {', '.join(sorted(options))} "
                             "(allowed: dt, t_end, save_every, max_steps, newton_tol, newton_max_iter)")
        scene = resolve_scene(scene)
        t_end = scene.t_end if t_end is None else t_end
        check_fixed_step(t_end, dt, save_every, max_steps)
        check_positive("newton_tol", newton_tol)
        if isinstance(newton_max_iter, bool) or not isinstance(newton_max_iter, (int, np.integer)) or newton_max_iter < 1:
            raise ValueError(f"newton_max_iter = {newton_max_iter!r} is invalid (allowed: an integer >= 1)")

        model, setup_time = build_model_timed(scene)  # a first build is setup: booked with compile time
        lay = model.layout
        guards, guards_time = guards_timed(model)  # the guards' thresholds: setup, booked with compile time
        setup_time += guards_time
        idx, n_run, truncated = step_indices(t_end, dt, save_every, max_steps)
        tc = time.perf_counter()
        x0, R0, w0 = (jnp.asarray(a) for a in model.initial_state())
        p0 = _mass_matrix_fn(model)(x0, R0, w0)  # compiled on first use: counted as compile time
        compile_p0 = time.perf_counter() - tc
        n_buf = bucket(len(idx))
        idx_buf = np.full(n_buf, idx[-1], dtype=np.int64)
        idx_buf[: len(idx)] = idx
        # numpy, not jnp: an eager int64 -> int32 conversion compiles on first use (~0.1 s each, in the run time)
        args = (x0, R0, p0, np.float64(dt), np.asarray(idx_buf, np.int32), np.int32(len(idx)),
                np.float64(newton_tol), np.int32(newton_max_iter), np.float64(guards.energy_bound),
                np.float64(CAYLEY_BOUND))
        compiled, compile_time = _compiled_run(model, n_buf, args, self.scheme)
        velocity, compile_v = _velocity_fn(model, n_buf, (np.zeros((n_buf, lay.nx)), np.zeros((n_buf, 3, 3)),
                                                          np.zeros((n_buf, lay.nw))))
        compile_time += compile_p0 + compile_v + setup_time
        bufs, j, stats = compiled(*args)
        V = np.asarray(velocity(bufs[0], bufs[1], bufs[2]))  # every slot; the kept ones are sliced below

        X, Rs, P, Ws, K = (np.asarray(b) for b in bufs)
        tot, mx, code, fail_k = (int(v) for v in stats)
        n = int(j)
        energy_note = ""
        if code == 4:  # the slot after the kept ones holds the state that failed the energy guard
            err = float(energy_error(model, jnp.asarray(X[n]), jnp.asarray(Rs[n]), jnp.asarray(V[n]), float(Ws[n]), guards.E0))
            kept = f"; trajectory kept up to the previous save point t = {K[n - 1] * dt:.6g} s"
            energy_note = energy_reason(err, guards.energy_bound, K[n] * dt, kept)
        X, Rs, P, Ws, K, V = X[:n], Rs[:n], P[:n], Ws[:n], K[:n], V[:n]
        if n >= 2 and K[-1] == K[-2]:  # failure right after a save: last slot repeats it
            X, Rs, P, Ws, K, V = X[:-1], Rs[:-1], P[:-1], Ws[:-1], K[:-1], V[:-1]
        steps = int(K[-1])
        status, reason = Status.OK.value, ""
        if code:
            status = _CODES[code].value
            t_fail = fail_k * dt
            what = {1: f"Newton did not converge within {newton_max_iter} iterations (tol {newton_tol:g}) "
                       "or produced a non-finite iterate",
                    2: "the new state is not finite",
                    3: f"the deployed length reached {model.length_limit_name(model.L - float(X[-1][0]) if lay.has_reel else 0.0)}",
                    4: "",
                    5: f"Cayley parameter blow-up: |c| > {CAYLEY_BOUND:g}, i.e. the body would rotate by more than "
                       f"{np.degrees(2 * np.arctan(CAYLEY_BOUND)):.0f} degrees in one step (step too large for the spin)"}[code]
            reason = f"step {fail_k + 1} (t = {t_fail:.6g} s -> {t_fail + dt:.6g} s): {what}"
            if code == 4:
                reason = energy_note
        elif truncated:
            status = Status.MAX_STEPS.value
            reason = f"stopped after max_steps = {max_steps} steps at t = {n_run * dt:.6g} s (t_end = {t_end:g} s)"
        if code == 1 and lay.has_attitude:  # the usual cause with a fast-spinning body, said plainly
            turn = float(dt * np.linalg.norm(V[-1][lay.omega]))
            if turn > 0.5:
                reason += (f"; h|Omega| = {turn:.3g} rad at the last kept state: the Cayley step "
                           "(2 J c/(1+|c|^2) ~ h Pi) has no solution beyond about 1 rad per step (a fast spin, or a "
                           "body spun up by a diverging string) - reduce dt")
        traj = Trajectory(
            t=K * dt, x=X, attitude=Rs if lay.has_attitude else None, velocity=V, work=Ws, momentum=P,
            attitude_kind="matrix", status=status, reason=reason,
            stats={"steps": steps, "newton_iterations": tot, "max_newton_iterations": mx,
                   "compile_time": compile_time, "rhs": "closed_form"},
            integrator=self.name,
            settings={"dt": float(dt), "t_end": float(t_end), "save_every": save_every, "max_steps": max_steps,
                      "newton_tol": float(newton_tol), "newton_max_iter": int(newton_max_iter), "rhs": "closed_form"},
            scene_name=scene.name,
        )
        stamp_wall_time(traj, started)
        traj.stats["time_per_step"] = traj.stats["wall_time"] / max(steps, 1)
        return traj
