"""The LGVI step, traced into the fixed-step lifecycle's loop (`integrators.fixed_step`).

One step of the paper's LGVI (docs/equations.md, "The LGVI step") solves the implicit p_k
equations for X = (Δs, Δq, c), F = cay(c), R_{k+1} = R_k F, then evaluates p_{k+1} explicitly.
The discrete Lagrangian and its structured solver (tridiagonal string rows + a Newton solve in
at most four unknowns (Δs, c)) are `integrators._lgvi_core`'s; this module is what one step
does with them: the Newton iteration, the symmetric scheme's forcing fixed point, the Cayley
guard and the composition of substeps. The loop, saving, guards, statuses and timing are the
lifecycle's.

The carry of a step is (x, R, p, ∇V, W, z): coordinates, attitude matrix, discrete momenta, the
potential gradient at g_k (reused by the next step), the accumulated work and the reduced
unknowns of the last two steps (Newton's first guess extrapolates them; one history per
substep in a composition).
"""

from __future__ import annotations

import functools

import numpy as np

from reelbench.integrators._lgvi_core import DiscreteLagrangian, cayley, small_solve
from reelbench.integrators.fixed_step import StepCode, StepResult
from reelbench.models._jax import jax, jnp

#: re-assemble the chord-Newton Jacobian when |dz| shrinks by less than this factor
CHORD_REFRESH = 0.1


def lgvi_step(model, scheme, cayley_code: int) -> "LGVIStep":
    """The step of ``scheme`` on ``model``, built once per pair; its constants are computed
    eagerly even when first asked for inside a trace (no tracer may be cached). A model bound
    to run-time values (`StringPendulum.bind`) gets a new step each time: its constants are
    computed in the trace that asks.
    ``cayley_code``: the `StepCode` of the Cayley guard (`integrators.lgvi` defines it)."""
    if model.is_bound:
        return LGVIStep(model, scheme, cayley_code)
    return _lgvi_step_cached(model, scheme, cayley_code)


@functools.lru_cache(maxsize=32)
def _lgvi_step_cached(model, scheme, cayley_code: int) -> "LGVIStep":
    with jax.ensure_compile_time_eval():
        return LGVIStep(model, scheme, cayley_code)


class LGVIStep:
    """The LGVI step of one model and `integrators.lgvi.Scheme`."""

    def __init__(self, model, scheme, cayley_code: int):
        self.model = model
        self.scheme = scheme
        self.cayley_code = cayley_code
        self.dl = DiscreteLagrangian(model, symmetric=scheme.symmetric)
        # the symmetric scheme's midpoint string force depends on the step: fixed point around
        # the structured solve (`DiscreteLagrangian.with_forcing`)
        self.lagged = self.dl.symmetric and self.dl.node_forced
        nz = self.dl.nz
        self.z_shape = (2, nz) if scheme.gammas is None else (len(scheme.gammas), 2, nz)

    def initial(self, x0, R0, p0):
        """The carry at g_0 with discrete momenta p_0."""
        gV0 = self.model.potential_gradient(x0, R0)
        return (x0, R0, p0, gV0, jnp.zeros((), jnp.float64), jnp.zeros(self.z_shape))

    # -------------------------------------------------------------------------------------
    def newton(self, ctx, p, h, z0, d, tol, maxit):
        """(Δs, c, F, Δq, iterations, ok, z) of the p_k equations for the forcing in ``ctx``.
        ``d`` (fixed length): the forward pass of the string rows' solve (`string_forward`);
        Newton reads its tip row, Δq is finished after it (`string_finish`).

        With a reel, chord-Newton: the exact reduced Jacobian is assembled on the first
        iteration and kept while the iteration contracts fast; later iterations only evaluate
        the residual (about a quarter of the cost: J needs a tangent Thomas pass). A slow
        contraction (ratio > CHORD_REFRESH) re-assembles J, so hard steps still get full
        Newton. Without a reel J is cheap: plain Newton. Fixed length with a point mass needs
        no Newton at all (one linear solve)."""
        dl = self.dl
        ps, pq, Pi = dl.split_momentum(p)
        uv = None if dl.reel else dl.tip_rows(d)
        if dl.nz == 0:
            dq = dl.string_finish(d, jnp.zeros(3))
            return (jnp.asarray(0.0), jnp.zeros(3), jnp.eye(3), dq, jnp.asarray(1, jnp.int32),
                    jnp.all(jnp.isfinite(dq)), z0)

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
            return jnp.where(bad, zz, zn), J, size, it_ + 1, size <= tol, bad, size > CHORD_REFRESH * dz_prev

        z_sol, _, _, it, conv, bad, _ = jax.lax.while_loop(
            cond, body, (z0, jnp.zeros((dl.nz, dl.nz)), jnp.asarray(jnp.inf), jnp.asarray(0, jnp.int32),
                         jnp.asarray(False), jnp.asarray(False), jnp.asarray(True)))
        ds, c = dl.unpack_z(z_sol)
        F = cayley(c) if dl.rigid else jnp.eye(3)
        if dl.reel:
            u, v = dl.string_solve(ctx, pq, h, ds)
            dq = u - v[:, None] * dl.body_term(ctx, F)[None, :]
        else:
            dq = dl.string_finish(d, dl.body_term(ctx, F))
        return ds, c, F, dq, it, conv & ~bad & jnp.all(jnp.isfinite(dq)), z_sol

    def midpoint_forcing(self, ctx, p, pq, h, first, tol, maxit):
        """The symmetric scheme's midpoint string force by fixed point: from the first solve
        (the paper's explicit force at g_k, `context`), re-solve with the midpoint force of the last
        iterate until Δx stops changing (contraction ≈ h γ_max / 2, see `with_forcing`).
        Returns the solve's (Δs, c, F, Δq, iterations, z), ok, and the final context."""
        dl = self.dl
        ds, c, F, dq, it, newton_ok, z_sol = first

        def fp_cond(c_):
            *_, n, conv, ok_ = c_
            return (~conv) & ok_ & (n < maxit)

        def fp_body(c_):
            ds_, c_prev, F_, dq_, it_, zz, n, _, _ = c_
            ctx_ = dl.with_forcing(ctx, h, ds_, dq_, c_prev)
            d_ = None if dl.reel else dl.string_forward(ctx_, pq, h)
            ds1, c1, F1, dq1, it1, ok1, z1 = self.newton(ctx_, p, h, zz, d_, tol, maxit)
            conv = (jnp.max(jnp.abs(dq1 - dq_)) <= tol) & (jnp.abs(ds1 - ds_) <= tol)
            if dl.body_forced:  # the body loads depend on the rotation too
                conv = conv & (jnp.max(jnp.abs(c1 - c_prev)) <= tol)
            return ds1, c1, F1, dq1, it_ + it1, z1, n + 1, conv, ok1

        ds, c, F, dq, it, z_sol, _, conv, ok = jax.lax.while_loop(
            fp_cond, fp_body, (ds, c, F, dq, it, z_sol, jnp.asarray(0, jnp.int32), jnp.asarray(False), newton_ok))
        return (ds, c, F, dq, it, z_sol), conv & ok, dl.with_forcing(ctx, h, ds, dq, c)

    # -------------------------------------------------------------------------------------
    def substep(self, x, R, p, gV, z, t, h, prm, check_state: bool):
        """One step of size h from (x, R, p): ((x1, R1, p1, ∇V1, ΔW, z), iterations, code).

        ``code``: `StepCode.NEWTON_FAILED`, the Cayley guard's code (|c| > bound: the body would
        turn by more than 90° in one step, beyond what the Cayley step resolves), or, with
        ``check_state`` (the inner substeps of a composition, whose states the lifecycle does
        not see), a non-finite state or the deployed length out of its range."""
        dl, model = self.dl, self.model
        tol, maxit = prm["newton_tol"], prm["newton_max_iter"]
        ctx = dl.context(t, x, R, gV, p)
        _, pq, _ = dl.split_momentum(p)
        d = None if dl.reel else dl.string_forward(ctx, pq, h)
        # the first guess extrapolates the last two steps' solutions, which saves one iteration
        z0 = 2.0 * z[1] - z[0] if dl.nz else z[1]
        first = self.newton(ctx, p, h, z0, d, tol, maxit)
        ds, c, F, dq, it, newton_ok, z_sol = first
        if self.lagged:
            (ds, c, F, dq, it, z_sol), newton_ok, ctx = self.midpoint_forcing(ctx, p, pq, h, first, tol, maxit)
        x1 = x + dl.step_vector(ds, dq)
        R1 = R @ F if dl.rigid else R
        gV1 = model.potential_gradient(x1, R1)
        p1 = dl.hp_k1(ctx, h, ds, dq, c, gV1, pq=pq) / h
        dW = dl.work(ctx, h, ds, dq, c)
        code = jnp.where(~newton_ok, StepCode.NEWTON_FAILED, 0)
        if check_state:
            finite = (jnp.all(jnp.isfinite(x1)) & jnp.all(jnp.isfinite(p1)) & jnp.all(jnp.isfinite(R1))
                      & jnp.isfinite(dW))
            code = jnp.where(code != 0, code, jnp.where(~finite, StepCode.NON_FINITE, jnp.where(
                ~(model.deployed_length_margin(x1) > 0), StepCode.LENGTH_LIMIT, 0)))
        if dl.rigid:  # the Cayley guard overrides all but a Newton failure and the length limit
            over = (code != StepCode.NEWTON_FAILED) & (code != StepCode.LENGTH_LIMIT) & (c @ c > prm["cayley_bound"] ** 2)
            code = jnp.where(over, self.cayley_code, code)
        return (x1, R1, p1, gV1, dW, jnp.stack([z[1], z_sol])), it, jnp.asarray(code, jnp.int32)

    def step(self, carry, t, h, prm):
        """One (macro) step of the scheme: ((x, R, p, ∇V, W, z), `StepResult`)."""
        x, R, p, gV, W, z = carry
        if self.scheme.gammas is None:
            (x1, R1, p1, gV1, dW, z1), it, code = self.substep(x, R, p, gV, z, t, h, prm, check_state=False)
            return (x1, R1, p1, gV1, W + dW, z1), StepResult(code, it)
        (x1, R1, p1, gV1, dW, z1), it, code = self.composition(x, R, p, gV, z, t, h, prm)
        return (x1, R1, p1, gV1, W + dW, z1), StepResult(code, it)

    def composition(self, x, R, p, gV, z, t, h, prm):
        """Φ_{γ_m h} ∘ … ∘ Φ_{γ_1 h}: substep i of size γ_i h starts at t + (γ_1 + … + γ_{i−1}) h
        and keeps its own Newton history (z[i]), since the sizes differ. A failed substep's
        successors still run (scan), but the macro step carries the first failure's code."""
        gammas = self.scheme.gammas
        gam = jnp.asarray(gammas)
        tau = jnp.asarray(np.concatenate([[0.0], np.cumsum(gammas)[:-1]]))

        def sub(acc, inp):
            x_, R_, p_, gV_, W_, it_, code_ = acc
            g, tt, zi = inp
            (x1, R1, p1, gV1, dW, z1), it1, code1 = self.substep(x_, R_, p_, gV_, zi, t + tt * h, g * h, prm,
                                                                  check_state=True)
            code1 = jnp.where(code_ == 0, code1, code_)
            return (x1, R1, p1, gV1, W_ + dW, it_ + it1, code1), z1

        init = (x, R, p, gV, jnp.asarray(0.0), jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32))
        (x1, R1, p1, gV1, dW, it, code), z1 = jax.lax.scan(sub, init, (gam, tau, z))
        return (x1, R1, p1, gV1, dW, z1), it, code
