"""Closed-form discrete equations of the LGVI (docs/equations.md, "The LGVI step") and their structured solver.

This module is the *discrete Lagrangian* piece of the LGVI, kept apart from the time loop
(`integrators.lgvi`) so that a different discrete Lagrangian (lumped mass, symmetric reel
terms) can replace it. Everything is written in "h·p" units (momenta times the step h).

Per step, with X = (Δs, Δq_2..Δq_{N+1}, c) and F = cay(c) = (I + ĉ)(I − ĉ)⁻¹:

* the q rows of the p_k equations form, for given (Δs, c), a *scalar* tridiagonal system
  over all N nodes (node N+1 included: its row has the extra mass m_b on the diagonal and the
  known body term m_b R_k (F − I) ρ_c on the right-hand side), solved by the Thomas algorithm
  in O(N);
* what is left is a reduced nonlinear system in z = (Δs if reel, c if rigid body), at most
  4 unknowns (the s_p row and the Π row), solved by Newton with a Jacobian assembled by the
  chain rule: the Cayley pieces in closed form (`cayley_apply_jac`, `cayley_moment_jac`), the
  Δs-derivative of the tridiagonal solve by forward mode through it. At a fixed length the
  string rows' matrix is a constant, factored once (`FixedTridiag`). Fixed length with a point
  mass needs no Newton at all (one linear solve per step).

`hp_k_full` / `hp_k1` give the full closed-form residual sides for testing against the
autodiff discrete Lagrangian (tests/test_lgvi.py).

Forcing (discrete Lagrange–d'Alembert, forces f⁻ in the p_k equations and f⁺ in the p_{k+1}
equations; the work of step k is (f⁻ + f⁺)·Δx / h):

* reel forces (Carnot, control; s_p row only): f⁻ = f⁺ = (h/2) Q(t_k, x_k, Δs/h), implicit
  in Δs, which is already a Newton unknown;
* string forces (axial damping, fluid drag; q rows and s_p row): evaluated *explicitly*, so that the
  string rows stay a scalar tridiagonal system with a known right-hand side:
  f⁻ = (h/2) Q(t_k, x_k, w_k) with w_k = M(g_k)⁻¹ p_k (the continuous Legendre transform of
  the discrete momentum, structured O(N) solve of `models.closed_form`), and
  f⁺ = (h/2) Q(t_{k+1}, x_{k+1}, ẋ̃_{k+1}) with the predicted velocity ẋ̃_{k+1} = 2Δx/h − ẋ_k
  (= ẋ_k + h ẍ_k of the step). This is the trapezoidal rule for the force with an Euler
  predictor (Heun): second order for a fixed length (the reel terms keep first order while
  the length changes). Being explicit, it is stable only while h γ_max < 2, γ_max the largest
  eigenvalue of M⁻¹ K_d (K_d = −∂Q/∂w; γ_max ≤ 12 c/(μ l²) for the consistent-mass string):
  a mode with rate γ is multiplied by 1 − hγ + (hγ)²/2 per step. The drag's rate is about
  ρ_f d C_n |u|/μ on the string (u the flow relative to it; `models.effects.Drag`). Measured (fixed_length point
  mass, N = 4, h = 5 ms, γ_max = 25.5 c): bounded at hγ_max = 1.95, blows up at 2.05.
  `node_forcing` / `end_forcing` / `work` are the pieces;
* body loads (`models.effects.Effect.body_loads`: forces that depend on R and Ω and a moment on
  the body, body frame): explicit like the string forces, the moment in the Π rows as −∂_η V is,
  f⁻ at (t_k, x_k, R_k, w_k) and f⁺ at (t_{k+1}, x_{k+1}, R_k F, w̃_{k+1}) with the predicted
  Ω̃_{k+1} = 2θ/h − Ω_k, θ = `rotation_vector`(c) the step's rotation (symmetric: both at the
  midpoint R_k cay(c/(1 + √(1 + |c|²))) with θ/h); their moment's work is ½ (M⁻ + M⁺)·θ
  (docs/equations.md, "Reel and string forcing").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from reelbench.models._jax import jax, jnp
from reelbench.models.closed_form import ClosedFormEOM
from reelbench.models.model import hat, vee

#: Tridiagonal systems up to this size are unrolled at trace time (fast for small N);
#: larger ones use lax.scan (bounded compile time).
UNROLL_MAX = 24


def cayley(c):
    """F = (I + ĉ)(I − ĉ)⁻¹ = ((1 − |c|²) I + 2 ĉ + 2 c cᵀ) / (1 + |c|²)."""
    cc = c @ c
    return ((1.0 - cc) * jnp.eye(3) + 2.0 * hat(c) + 2.0 * jnp.outer(c, c)) / (1.0 + cc)


def rotation_vector(c):
    """θ with F = cay(c) = exp(θ^): θ = 2 atan(|c|) c/|c| (|c| = tan(|θ|/2)); its series
    2 c (1 − |c|²/3 + |c|⁴/5) near c = 0, where the quotient would lose digits (and its
    derivative would be NaN at 0)."""
    cc = c @ c
    small = cc < 1e-6
    r = jnp.sqrt(jnp.where(small, 1.0, cc))
    factor = jnp.where(small, 2.0 * (1.0 - cc / 3.0 + cc * cc / 5.0), 2.0 * jnp.arctan(r) / r)
    return factor * c


def cayley_apply_jac(c, rho):
    """(F ρ, ∂(F ρ)/∂c) for F = cay(c), in closed form (the derivative of `cayley`'s formula):
    with n = (1 − |c|²) ρ + 2 c × ρ + 2 c (c·ρ) and d = 1 + |c|²,
    ∂(n/d)/∂c = (2 c ρᵀ − 2 ρ cᵀ − 2 ρ^ + 2 (c·ρ) I) / d − n (2 cᵀ) / d²."""
    d = 1.0 + c @ c
    cr = c @ rho
    n = (2.0 - d) * rho + 2.0 * jnp.cross(c, rho) + 2.0 * cr * c
    dn = 2.0 * (jnp.outer(c, rho) - jnp.outer(rho, c) - hat(rho) + cr * jnp.eye(3))
    return n / d, dn / d - jnp.outer(n, 2.0 * c) / (d * d)


def cayley_moment_jac(c, J):
    """(m, ∂m/∂c) of m = (F J_d − J_d Fᵀ)^∨ = 2 (J c + c × J c) / (1 + |c|²), J = J_o, in
    closed form: ∂m/∂c = 2 (J + ĉ J − (J c)^) / d − m (2 cᵀ) / d."""
    d = 1.0 + c @ c
    Jc = J @ c
    m = 2.0 * (Jc + jnp.cross(c, Jc)) / d
    return m, 2.0 * (J + hat(c) @ J - hat(Jc)) / d - jnp.outer(m, 2.0 * c) / d


def small_solve(J, r):
    """J⁻¹ r for a small (n ≤ 4) system by unrolled Gaussian elimination without pivoting.

    The LGVI's reduced Jacobian is close to blockdiag(M0, 2 J_c) (positive definite), so no
    pivoting is needed; unrolling avoids a LAPACK call per Newton iteration.
    """
    n = r.shape[0]
    A = [[J[i, j] for j in range(n)] for i in range(n)]
    b = [r[i] for i in range(n)]
    for k in range(n):
        inv = 1.0 / A[k][k]
        for i in range(k + 1, n):
            f = A[i][k] * inv
            for j in range(k + 1, n):
                A[i][j] = A[i][j] - f * A[k][j]
            b[i] = b[i] - f * b[k]
    x = [None] * n
    for i in range(n - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, n):
            acc = acc - A[i][j] * x[j]
        x[i] = acc / A[i][i]
    return jnp.stack(x)


def tridiag_solve(sub, diag, sup, rhs):
    """Thomas algorithm for rows i: sub_i y_{i-1} + diag_i y_i + sup_i y_{i+1} = rhs_i.

    sub, diag, sup: (n,); rhs: (n, k). sub_0 and sup_{n-1} are ignored. No pivoting: the
    LGVI's matrix is strictly diagonally dominant (consistent mass matrix).
    """
    n = diag.shape[0]
    if n <= UNROLL_MAX:
        cp, dp = [], []
        c_prev = None
        d_prev = None
        for i in range(n):
            if i == 0:
                den = diag[0]
                d_i = rhs[0] / den
            else:
                den = diag[i] - sub[i] * c_prev
                d_i = (rhs[i] - sub[i] * d_prev) / den
            c_i = sup[i] / den
            cp.append(c_i)
            dp.append(d_i)
            c_prev, d_prev = c_i, d_i
        ys = [None] * n
        ys[n - 1] = dp[n - 1]
        for i in range(n - 2, -1, -1):
            ys[i] = dp[i] - cp[i] * ys[i + 1]
        return jnp.stack(ys)

    def fwd(carry, row):
        c_prev, d_prev = carry
        a, b, c, d = row
        den = b - a * c_prev
        c_i = c / den
        d_i = (d - a * d_prev) / den
        return (c_i, d_i), (c_i, d_i)

    sub0 = sub.at[0].set(0.0)
    init = (jnp.zeros((), rhs.dtype), jnp.zeros(rhs.shape[1:], rhs.dtype))
    _, (cp, dp) = jax.lax.scan(fwd, init, (sub0, diag, sup, rhs), unroll=8)

    def bwd(y_next, row):
        c_i, d_i = row
        y = d_i - c_i * y_next
        return y, y

    _, ys = jax.lax.scan(bwd, jnp.zeros(rhs.shape[1:], rhs.dtype), (cp, dp), reverse=True, unroll=8)
    return ys


class FixedTridiag:
    """The string rows' matrix at a fixed length, A = mul·T + m_b e_N e_Nᵀ (T = tri(sub, diag,
    sup) of the mass model, numpy; mul = μ l and m_b may be run-time values), factored once.

    The Thomas factors of A follow from T's alone: for rows i < N, den_i = mul·den_i(T) and
    cp_i = cp_i(T); the last row's den is mul·den_N(T) + m_b (its cp is 0: sup_N = 0). So a
    solve is two first-order linear recurrences with coefficients computed elementwise
    (d_i = a_i d_{i-1} + r_i / den_i, then y_i = b_i y_{i+1} + d_i) and no divisions in them;
    ``ends`` = A⁻¹ e_N (the tip column, which the body term multiplies) is (1/den_N) times the
    products of the b_i, also T's.
    """

    def __init__(self, sub, diag, sup, mul, m_b):
        sub, diag, sup = (np.asarray(a, dtype=float) for a in (sub, diag, sup))
        n = diag.shape[0]
        den_t, cp = np.empty(n), np.empty(n)
        prev = 0.0
        for i in range(n):
            den_t[i] = diag[i] - (sub[i] * prev if i else 0.0)
            cp[i] = sup[i] / den_t[i]
            prev = cp[i]
        xp = np if all(isinstance(v, (float, int, np.floating, np.ndarray)) for v in (mul, m_b)) else jnp
        last = np.zeros(n)
        last[-1] = 1.0
        self.invden = 1.0 / (mul * den_t + m_b * last)
        first = np.ones(n)
        first[0] = 0.0  # each pass's starting row has no predecessor
        self.fwd = -(mul * (sub * first)) * self.invden
        self.bwd = -cp
        self.bwd[-1] = 0.0
        # A⁻¹ e_N: y_N = 1/den_N, y_i = b_i y_{i+1}
        tail = np.ones(n)
        for i in range(n - 2, -1, -1):
            tail[i] = self.bwd[i] * tail[i + 1]
        self.ends = self.invden[-1] * tail
        self._xp = xp

    def __call__(self, rhs):
        """A⁻¹ rhs, rhs (n, k)."""
        return self.backward(self.forward(rhs))

    def forward(self, rhs):
        """The forward pass d (n, k): d_i = a_i d_{i-1} + r_i / den_i. Its last row is already
        the solution's (y_n = d_n), and a change δ of the last right-hand side row changes it by
        δ / den_n only: what the LGVI's Newton iteration reads (`DiscreteLagrangian.tip_rows`)."""
        # the scale as an (n, k) constant: an elementwise product of equal shapes costs XLA CPU
        # ~2.5x less than the broadcast of an (n, 1) column (measured at n = 640, k = 3)
        d0 = rhs * self._xp.repeat(self.invden[:, None], rhs.shape[1], axis=1)
        return self._recurrence(self.fwd, d0, reverse=False)

    def backward(self, d):
        """The back substitution y (n, k) from the forward pass: y_i = b_i y_{i+1} + d_i."""
        return self._recurrence(self.bwd, d, reverse=True)

    @staticmethod
    def _recurrence(coeff, r, reverse: bool):
        """out_i = coeff_i out_{i∓1} + r_i (coeff of the starting row is 0), unrolled at trace
        time up to `UNROLL_MAX` rows, else a lax.scan."""
        n = r.shape[0]
        if n <= UNROLL_MAX:
            order = range(n - 1, -1, -1) if reverse else range(n)
            out = [None] * n
            prev = None
            for i in order:
                out[i] = r[i] if prev is None else coeff[i] * prev + r[i]
                prev = out[i]
            return jnp.stack(out)

        def rec(prev, row):
            a, x = row
            y = a * prev + x
            return y, y

        _, out = jax.lax.scan(rec, jnp.zeros(r.shape[1:], r.dtype), (jnp.asarray(coeff), r), reverse=reverse)
        return out


@dataclass
class StepContext:
    """Quantities of g_k used by one step (mass terms at g_k)."""

    t: jnp.ndarray
    x: jnp.ndarray
    R: jnp.ndarray
    s: jnp.ndarray
    l: jnp.ndarray
    M0: jnp.ndarray
    C: jnp.ndarray  # (N, 3): C_a = M31_a + M23_{a-1}, coefficient of Δs in row a = 2..N+1
    dVs: jnp.ndarray
    dVq: jnp.ndarray  # (N, 3)
    dVeta: jnp.ndarray  # (3,)
    # explicit string forcing at g_k (axial damping; zeros without it), see `node_forcing`
    w: jnp.ndarray  # (nw,) velocity w_k = M(g_k)⁻¹ p_k
    fs: jnp.ndarray  # Q_s(t_k, x_k, w_k)
    fq: jnp.ndarray  # (N, 3) Q_q(t_k, x_k, w_k)
    feta: jnp.ndarray  # (3,) Q_Ω (zero for the string forces so far)


jax.tree_util.register_dataclass(
    StepContext, data_fields=["t", "x", "R", "s", "l", "M0", "C", "dVs", "dVq", "dVeta", "w", "fs", "fq", "feta"],
    meta_fields=[]
)


class DiscreteLagrangian:
    """Closed-form derivatives of the LGVI's L_d for one model (string mass of `string.mass_model`).

    ``symmetric=False``: the paper's LGVI (s_p-dependent mass terms and the forcing at
    g_k; first order while the length changes). ``symmetric=True``: the symmetric LGVI
    (docs/equations.md, "The symmetric LGVI"), L_d^sym = L_d
    + C(Δx)/h (mass terms at the step midpoint) with every force evaluated once at the midpoint
    with the secant velocity, f⁻ = f⁺ = (h/2) Q(t_k + h/2, x_{k+½}, Δx/h): the forced map is
    self-adjoint, hence second order everywhere (and composable to higher order). The two
    differ only in `q_coeffs` (l_{k+1} in the consistent mass), `hp_s`, `hp_k1` (the ∇C terms),
    the reel forcing (`forcing`) and the string forcing (`end_forcing`, `with_forcing`). At
    fixed length without string forces both are the same computation (C ∝ Δs = 0).
    """

    def __init__(self, model, symmetric: bool = False):
        self.model = model
        self.symmetric = bool(symmetric)
        lay = model.layout
        self.N = N = model.N
        self.reel = lay.has_reel
        self.rigid = lay.has_attitude
        self.nw = lay.nw
        self.nz = (1 if self.reel else 0) + (3 if self.rigid else 0)
        mu = model.mu
        a = np.arange(2, N + 2, dtype=float)  # nodes 2..N+1
        last = np.zeros(N)
        last[-1] = 1.0
        self.e_last = jnp.asarray(last)
        # nonlinear Δs terms of the q rows, coefficient μΔs/(6N) times these
        cprev = 5 + 3 * N - 3 * a
        cself = np.full(N, 2.0)
        cnext = -(1 + 3 * N - 3 * a)
        cprev[-1], cself[-1], cnext[-1] = 2.0, 1.0, 0.0
        self.cprev, self.cself, self.cnext = (jnp.asarray(v * mu / (6 * N)) for v in (cprev, cself, cnext))
        # string mass coefficients, times μ l (models.model.STRING_MASS: consistent 1/6, 2/3,
        # 1/3; lumped 0, 1, 1/2 — the lumped one only at fixed length, so C and M0 stay unused)
        sm = model.string_mass
        self.msub = jnp.full(N, sm.o / sm.den)
        self.mdiag = jnp.asarray(np.where(last > 0, sm.d / sm.den, 2.0 * sm.d / sm.den))
        self.msup = jnp.asarray(np.where(last > 0, 0.0, sm.o / sm.den))
        self.c31 = jnp.asarray(model.c31)
        self.c23 = jnp.asarray(model.c23)
        self.rho = jnp.asarray(model.rho_c)
        self.J_o = jnp.asarray(model.J_o)
        self.J_d = jnp.asarray(model.J_d)
        #: body loads present (`Effect.body_loads`): forces that depend on R and Ω and may put a
        #: moment on the body; explicit like the string forces, and their f⁺ needs the rotation
        self.body_forced = bool(model.body_loads) and self.rigid
        #: string forces (axial damping) or body loads present: explicit forcing from w_k = M⁻¹ p_k
        self.node_forced = bool(model.string_forces) or bool(model.body_loads)
        #: w = M(x, R)⁻¹ p by the structured O(N) solve (string forcing, the LGVI's energy guard)
        self.legendre = ClosedFormEOM(model).velocity_from_momentum
        #: at a fixed length the string rows' matrix is a constant: factored once
        self.fixed_rows = None if self.reel else FixedTridiag(
            *self._mass_rows(), self.model.mu * (self.model.L - self.model.s_fixed) / self.N, self.model.m_b)

    def _mass_rows(self):
        """(sub, diag, sup) of the q rows' string mass in units of μ l (numpy: the mass model's)."""
        sm = self.model.string_mass
        N = self.N
        last = np.arange(N) == N - 1
        return (np.full(N, sm.o / sm.den), np.where(last, sm.d / sm.den, 2.0 * sm.d / sm.den),
                np.where(last, 0.0, sm.o / sm.den))

    # -------------------------------------------------------------------------------------
    def context(self, t, x, R, gradV, p=None) -> StepContext:
        """Quantities of g_k; ``p`` (p_k) is needed only for the string forces (`node_forcing`)."""
        m = self.model
        N = self.N
        q = m.nodes(x)
        s = m.reel_coordinate(x)
        l = (m.L - s) / N
        M0 = m.reel_mass(s)  # the one definition (StringPendulum.reel_mass)
        if self.reel:
            D = q[:-1] - q[1:]  # (N, 3), q_a - q_{a+1}
            M31 = self.c31[:, None] * D
            M23 = self.c23[:, None] * D
            C = M23 + jnp.concatenate([M31[1:], jnp.zeros((1, 3))], axis=0)
            dVs = gradV[0]
        else:
            C = jnp.zeros((N, 3))
            dVs = jnp.asarray(0.0)
        lay = m.layout
        dVq = gradV[lay.nodes].reshape(N, 3)
        dVeta = gradV[lay.omega] if self.rigid else jnp.zeros(3)
        w, (fs, fq, feta) = self.node_forcing(t, x, R, p)
        return StepContext(t=t, x=x, R=R, s=s, l=l, M0=M0, C=C, dVs=dVs, dVq=dVq, dVeta=dVeta,
                           w=w, fs=fs, fq=fq, feta=feta)

    # -------------------------------------------------------------------------------------
    # Explicit string forcing (axial damping); zeros without string forces
    # -------------------------------------------------------------------------------------
    def split_force(self, Q):
        """Q over w's layout -> (Q_s, Q_q (N, 3), Q_Ω) (zeros for absent coordinates)."""
        return self.split_momentum(Q)

    def node_forcing(self, t, x, R, p):
        """(w_k, (Q_s, Q_q, Q_Ω)) at g_k with w_k = M(g_k)⁻¹ p_k: the explicit f⁻ = (h/2) Q."""
        if not self.node_forced:
            return jnp.zeros(self.nw), (jnp.asarray(0.0), jnp.zeros((self.N, 3)), jnp.zeros(3))
        if p is None:
            raise ValueError("DiscreteLagrangian.context needs p_k when the model has string forces")
        w = self.legendre(x, R, p)
        return w, self.split_force(self.model.loads(t, x, R, w))

    def step_vector(self, ds, dq):
        """Δx over x's layout."""
        return jnp.concatenate([jnp.atleast_1d(ds), dq.ravel()]) if self.reel else dq.ravel()

    def midpoint(self, ctx: StepContext, h, ds, dq):
        """(t_k + h/2, x_{k+½}, secant velocity) of the symmetric forcing.

        The Ω slot of the velocity is zero: the reel and string forces act on (s_p, q) and depend
        on Ω not at all (the body loads take `body_midpoint`).
        """
        dx = self.step_vector(ds, dq)
        w = jnp.concatenate([dx / h, jnp.zeros(self.nw - dx.shape[0])])
        return ctx.t + 0.5 * h, ctx.x + 0.5 * dx, w

    def body_midpoint(self, ctx: StepContext, h, ds, dq, c):
        """(t_k + h/2, x_{k+½}, R_{k+½}, secant velocity) of the symmetric body loads: the attitude
        halfway along the step's rotation, R_k cay(c/(1 + √(1 + |c|²))) (half the angle), and the
        secant angular velocity θ/h, θ = `rotation_vector`(c)."""
        t, x, w = self.midpoint(ctx, h, ds, dq)
        half = c / (1.0 + jnp.sqrt(1.0 + c @ c))
        w = jax.lax.dynamic_update_slice(w, rotation_vector(c) / h, (self.model.layout.omega.start,))
        return t, x, ctx.R @ cayley(half), w

    def end_forcing(self, ctx: StepContext, h, ds, dq, c=None):
        """(Q_s, Q_q, Q_Ω) of f⁺ = (h/2) Q⁺.

        Paper's: Q⁺ = Q(t_k + h, x_{k+1}, 2Δx/h − ẋ_k) (Heun predictor); with body loads also at
        R_{k+1} = R_k cay(c) and the predicted Ω̃_{k+1} = 2θ/h − Ω_k, θ = `rotation_vector`(c).
        Symmetric: Q⁺ = Q⁻ = Q(t_k + h/2, x_{k+½}, Δx/h) (with body loads at R_{k+½} and θ/h:
        `body_midpoint`), the same midpoint force on both ends. ``c`` is needed with body loads.
        """
        if not self.node_forced:
            return jnp.asarray(0.0), jnp.zeros((self.N, 3)), jnp.zeros(3)
        if self.body_forced:
            if c is None:
                raise ValueError("DiscreteLagrangian.end_forcing: body loads need the step's rotation c")
            if self.symmetric:
                return self.split_force(self.model.loads(*self.body_midpoint(ctx, h, ds, dq, c)))
            nx = self.model.layout.nx
            dx = self.step_vector(ds, dq)
            w1 = jnp.concatenate([2.0 * dx / h - ctx.w[:nx], 2.0 * rotation_vector(c) / h - ctx.w[nx:]])
            return self.split_force(self.model.loads(ctx.t + h, ctx.x + dx, ctx.R @ cayley(c), w1))
        if self.symmetric:
            tm, xm, wm = self.midpoint(ctx, h, ds, dq)
            return self.split_force(self.model.loads(tm, xm, ctx.R, wm))
        nx = self.model.layout.nx
        dx = self.step_vector(ds, dq)
        w1 = jnp.concatenate([2.0 * dx / h - ctx.w[:nx], ctx.w[nx:]])
        return self.split_force(self.model.loads(ctx.t + h, ctx.x + dx, ctx.R, w1))

    def with_forcing(self, ctx: StepContext, h, ds, dq, c=None) -> StepContext:
        """The symmetric scheme's context with f⁻ = (h/2) Q(t_k + h/2, x_{k+½}, Δx/h) at (Δs, Δq).

        The midpoint string force depends on the step itself, and through the element
        directions it is not a scalar times I₃: solving it inside the tridiagonal system would
        cost a 3×3-block solve. The step instead lags it by one iteration (fixed point around the
        scalar solve, `integrators.lgvi`), which contracts by about h γ_max / 2 per iteration:
        the paper's explicit forcing's stability limit h γ_max < 2, met with iterations instead of a
        blow-up. ``ctx`` is returned unchanged without string forces or for the paper's scheme.
        """
        if not (self.symmetric and self.node_forced):
            return ctx
        fs, fq, feta = self.end_forcing(ctx, h, ds, dq, c)
        return dataclasses.replace(ctx, fs=fs, fq=fq, feta=feta)

    def work(self, ctx: StepContext, h, ds, dq, c=None):
        """Work of the forcing on step k: Q_k Δs (reel) + ½ (Q⁻ + Q⁺)·Δx (string forces and body
        loads) + ½ (M⁻ + M⁺)·θ (the body loads' moments, θ = `rotation_vector`(c) the step's
        rotation in the body frame).

        Symmetric: Q_{k+½} Δs + Q_{k+½}·Δx + M_{k+½}·θ, the same forces as in f⁻ and f⁺.
        """
        dW = self.forcing(ctx, ds, h, dq) * ds
        if self.node_forced:
            fs1, fq1, feta1 = self.end_forcing(ctx, h, ds, dq, c)
            dW = dW + 0.5 * jnp.sum((ctx.fq + fq1) * dq)
            if self.reel:
                dW = dW + 0.5 * (ctx.fs + fs1) * ds
            if self.body_forced:
                dW = dW + 0.5 * (ctx.feta + feta1) @ rotation_vector(c)
        return dW

    def split_momentum(self, p):
        lay = self.model.layout
        ps = p[0] if self.reel else jnp.asarray(0.0)
        pq = p[lay.nodes].reshape(self.N, 3)
        Pi = p[lay.omega] if self.rigid else jnp.zeros(3)
        return ps, pq, Pi

    def join(self, ps, pq, Pi):
        parts = ([jnp.atleast_1d(ps)] if self.reel else []) + [pq.ravel()] + ([Pi] if self.rigid else [])
        return jnp.concatenate(parts)

    def unpack_z(self, z):
        ds = z[0] if self.reel else jnp.asarray(0.0)
        c = z[self.nz - 3:] if self.rigid else jnp.zeros(3)
        return ds, c

    def pack_z(self, ds, c):
        parts = ([jnp.atleast_1d(ds)] if self.reel else []) + ([c] if self.rigid else [])
        return jnp.concatenate(parts) if parts else jnp.zeros(0)

    # -------------------------------------------------------------------------------------
    def forcing(self, ctx: StepContext, ds, h, dq=None):
        """The reel force of the step: paper's Q_k = Q_u(t_k) + Q_c(s_k, Δs/h, q_{k,2}); symmetric
        Q_{k+½} = Q_u(t_k + h/2) + Q_c(s_{k+½}, Δs/h, q_{k+½,2}) (needs ``dq``)."""
        if not self.reel or not self.model.reel_forces:
            return jnp.asarray(0.0)
        if self.symmetric:
            if dq is None:
                raise ValueError("DiscreteLagrangian.forcing: the symmetric scheme needs dq (its midpoint state)")
            return self.model.reel_force(*self.midpoint(ctx, h, ds, dq))
        w = jnp.zeros(self.nw).at[0].set(ds / h)
        return self.model.reel_force(ctx.t, ctx.x, w)

    def body_term(self, ctx: StepContext, F):
        """m_b R_k (F − I) ρ_c (zero without a rigid body)."""
        if not self.rigid:
            return jnp.zeros(3)
        return self.model.m_b * (ctx.R @ (F @ self.rho - self.rho))

    def q_coeffs(self, ctx: StepContext, ds):
        """Tridiagonal (sub, diag, sup) of the q rows of the p_k equations, in h·p units.

        Symmetric: the consistent-mass part at l_{k+1} = l_k − Δs/N.
        """
        mul = self.model.mu * (ctx.l - ds / self.N if self.symmetric else ctx.l)
        sub = mul * self.msub + ds * self.cprev
        diag = mul * self.mdiag + self.model.m_b * self.e_last + ds * self.cself
        sup = mul * self.msup + ds * self.cnext
        return sub, diag, sup

    def solve_dq(self, ctx: StepContext, pq, h, ds, F):
        """Δq_2..Δq_{N+1} from the q rows of the p_k equations, for given (Δs, F)."""
        sub, diag, sup = self.q_coeffs(ctx, ds)
        rhs = h * pq - ctx.C * ds - (0.5 * h * h) * (ctx.dVq - ctx.fq)
        rhs = rhs - self.e_last[:, None] * self.body_term(ctx, F)[None, :]
        return tridiag_solve(sub, diag, sup, rhs)

    def hp_s(self, ctx: StepContext, h, ds, dq):
        """h p_{s,k} side of the s_p row as a function of (Δs, Δq).

        Symmetric: −(μ/3)Δs² + (μ/6N) Σ quad_a becomes +(μ/6)Δs² (the Δq-quadratic cancels).
        """
        mu = self.model.mu
        Q = self.forcing(ctx, ds, h, dq)
        if self.symmetric:
            return ctx.M0 * ds + jnp.sum(ctx.C * dq) + mu / 6.0 * ds * ds + 0.5 * h * h * (ctx.dVs - Q - ctx.fs)
        return (ctx.M0 * ds + jnp.sum(ctx.C * dq) - mu / 3.0 * ds * ds + mu / (6 * self.N) * self._quad(dq)
                + 0.5 * h * h * (ctx.dVs - Q - ctx.fs))

    @staticmethod
    def _quad(dq):
        """Σ_a |Δq_a|² + Δq_a·Δq_{a+1} + |Δq_{a+1}|² (Δq_1 = 0)."""
        dqf = jnp.concatenate([jnp.zeros((1, 3)), dq], axis=0)
        da, db = dqf[:-1], dqf[1:]
        return jnp.sum(da * da) + jnp.sum(db * db) + jnp.sum(da * db)

    def hp_Pi(self, ctx: StepContext, h, c, dq_tip):
        """h Π_k side: (F J_d − J_d Fᵀ)^∨ + m_b ρ × R_kᵀ Δq_{N+1} + (h²/2) ∂_η V_k.

        (F J_d − J_d Fᵀ)^∨ = 2 (J_o c + c × J_o c) / (1 + |c|²) for F = cay(c).
        """
        Jc = self.J_o @ c
        rot = 2.0 * (Jc + jnp.cross(c, Jc)) / (1.0 + c @ c)
        return rot + self.model.m_b * jnp.cross(self.rho, ctx.R.T @ dq_tip) + 0.5 * h * h * (ctx.dVeta - ctx.feta)

    def string_solve(self, ctx: StepContext, pq, h, ds):
        """(u, v) with Δq = u − v ⊗ b for the body term b = m_b R_k (F − I) ρ_c.

        One Thomas pass with four right-hand sides:
        A(Δs) [u | v] = [h p_q − C Δs − (h²/2)(∇_q V_k − Q_q,k) | e_N]  (Q_q,k: explicit string forcing).
        """
        rhs = self.string_rhs(ctx, pq, h, ds)
        if self.fixed_rows is not None:
            return self.fixed_rows(rhs), jnp.asarray(self.fixed_rows.ends)
        sub, diag, sup = self.q_coeffs(ctx, ds)
        sol = tridiag_solve(sub, diag, sup, jnp.concatenate([rhs, self.e_last[:, None]], axis=1))
        return sol[:, :3], sol[:, 3]

    def string_rhs(self, ctx: StepContext, pq, h, ds):
        """h p_q − C Δs − (h²/2)(∇_q V_k − Q_q,k): the string rows' right-hand side without the body term."""
        rhs = h * pq - (0.5 * h * h) * (ctx.dVq - ctx.fq if self.node_forced else ctx.dVq)
        return rhs - ctx.C * ds if self.reel else rhs

    # -- the fixed-length step's split solve: forward pass, Newton on the tip row, back substitution
    def string_forward(self, ctx: StepContext, pq, h):
        """Fixed length: the forward pass of the string rows' solve, before the body term is known."""
        return self.fixed_rows.forward(self.string_rhs(ctx, pq, h, 0.0))

    def tip_rows(self, d):
        """(u, v) of `string_solve` at the tip row alone, from the forward pass ``d``: all that the
        Newton iteration reads at a fixed length (Δq_{N+1} = u_{N+1} − v_{N+1} b)."""
        return d[-1:], jnp.asarray(self.fixed_rows.ends[-1:])

    def string_finish(self, d, b):
        """Δq from the forward pass and the body term b (zeros without a body): b enters the
        last row's right-hand side only, which changes d_N by −b / den_N; then the back
        substitution. Equal to u − v ⊗ b without the outer product (a pass over N × 3)."""
        return self.fixed_rows.backward(d.at[-1].add(-self.fixed_rows.invden[-1] * b))

    def body_of_c(self, ctx: StepContext, c):
        return self.body_term(ctx, cayley(c))

    def reduced_system(self, ctx: StepContext, p, h, z, uv=None):
        """Residual r(z) and Jacobian J(z) of the reduced system in z = (Δs, c).

        The string rows are eliminated exactly: Δq(Δs, c) = u(Δs) − v(Δs) ⊗ b(c). With a reel,
        (u, v) and their Δs-derivatives come from one Thomas pass (forward-mode through it);
        without a reel, A is independent of z and ``uv`` = (u, v) is passed in, computed once
        per step, or their tip rows alone (`tip_rows`: all the Π row reads; the Δq returned is
        then the tip row). The Jacobian is assembled by the chain rule from small closed-form pieces.
        """
        ps, pq, Pi = self.split_momentum(p)
        ds, c = self.unpack_z(z)
        if self.reel:
            (u, v), (du, dv) = jax.jvp(lambda s_: self.string_solve(ctx, pq, h, s_), (ds,), (jnp.ones_like(ds),))
        else:
            u, v = uv
            du, dv = jnp.zeros_like(u), jnp.zeros_like(v)
        if self.rigid:  # b = m_b R_k (F − I) ρ_c and ∂b/∂c, in closed form (no autodiff per iteration)
            Frho, dFrho = cayley_apply_jac(c, self.rho)
            b = self.model.m_b * (ctx.R @ (Frho - self.rho))
            Bc = self.model.m_b * (ctx.R @ dFrho)
        else:
            b, Bc = jnp.zeros(3), jnp.zeros((3, 3))
        dq = u - v[:, None] * b[None, :]
        dq_ds = du - dv[:, None] * b[None, :]
        r, rows = [], []
        if self.reel:
            val, (g_s, g_q) = jax.value_and_grad(lambda s_, q_: self.hp_s(ctx, h, s_, q_), argnums=(0, 1))(ds, dq)
            r.append(jnp.atleast_1d(val - h * ps))
            row = [jnp.atleast_1d(g_s + jnp.sum(g_q * dq_ds))]
            if self.rigid:
                row.append(-(v @ g_q) @ Bc)
            rows.append(jnp.concatenate(row))
        if self.rigid:
            # hp_Pi = moment(c) + m_b ρ × R_kᵀ Δq_tip + const: its derivatives in closed form
            _, P_c = cayley_moment_jac(c, self.J_o)
            P_t = self.model.m_b * (hat(self.rho) @ ctx.R.T)
            r.append(self.hp_Pi(ctx, h, c, dq[-1]) - h * Pi)
            blk = P_c - v[-1] * (P_t @ Bc)
            if self.reel:
                blk = jnp.concatenate([(P_t @ dq_ds[-1])[:, None], blk], axis=1)
            rows.append(blk)
        return jnp.concatenate(r), jnp.concatenate([jnp.atleast_2d(x) for x in rows], axis=0), dq

    def reduced_residual(self, ctx: StepContext, p, h, z, uv=None):
        """Residual of the reduced system in z = (Δs, c) by direct elimination.

        The chord iterations of the LGVI step use it; ``uv`` (fixed length only) reuses the
        per-step string solve or its tip rows, as in `reduced_system`.
        """
        ps, pq, Pi = self.split_momentum(p)
        ds, c = self.unpack_z(z)
        F = cayley(c) if self.rigid else jnp.eye(3)
        if uv is None:
            dq = self.solve_dq(ctx, pq, h, ds, F)
        else:
            dq = uv[0] - uv[1][:, None] * self.body_term(ctx, F)[None, :]
        r = []
        if self.reel:
            r.append(jnp.atleast_1d(self.hp_s(ctx, h, ds, dq) - h * ps))
        if self.rigid:
            r.append(self.hp_Pi(ctx, h, c, dq[-1]) - h * Pi)
        return jnp.concatenate(r), dq

    # -------------------------------------------------------------------------------------
    def hp_k_full(self, ctx: StepContext, h, ds, dq, c):
        """Full closed-form h·p_k as a function of X (w's layout), for tests."""
        F = cayley(c) if self.rigid else jnp.eye(3)
        sub, diag, sup = self.q_coeffs(ctx, ds)
        dqf = jnp.concatenate([jnp.zeros((1, 3)), dq, jnp.zeros((1, 3))], axis=0)
        rows = sub[:, None] * dqf[:-2] + diag[:, None] * dqf[1:-1] + sup[:, None] * dqf[2:]
        rows = rows + ctx.C * ds + 0.5 * h * h * (ctx.dVq - ctx.fq) + self.e_last[:, None] * self.body_term(ctx, F)[None, :]
        hps = self.hp_s(ctx, h, ds, dq) if self.reel else 0.0
        hPi = self.hp_Pi(ctx, h, c, dq[-1]) if self.rigid else jnp.zeros(3)
        return self.join(hps, rows, hPi)

    def hp_k1(self, ctx: StepContext, h, ds, dq, c, gradV1, pq=None):
        """h·p_{k+1} (w's layout) from the step X and ∇V(g_{k+1}) (symmetric:
        the consistent mass at l_{k+1}, +(μ/2)Δs² − (μ/6N) Σ quad_a in the s_p row, Q_{k+½}).

        ``pq`` (p_k's q rows, fixed length only): the q rows of p_k and p_{k+1} then share their
        matrix, A Δq + e_N b = h p_q,k − (h²/2)(∇_q V_k − Q_q,k) (the rows the step solved), so
        h p_q,k+1 = h p_q,k − (h²/2)(∇_q V_k − Q_q,k + ∇_q V_{k+1} − Q⁺_q): the Störmer–Verlet
        form, without the tridiagonal product (equal to round-off; not with the lagged
        symmetric forcing, whose last context is one iterate newer than the solve)."""
        F = cayley(c) if self.rigid else jnp.eye(3)
        N, lay = self.N, self.model.layout
        mu = self.model.mu
        if pq is not None and self.fixed_rows is not None and not (self.symmetric and self.node_forced):
            lin = self.string_rhs(ctx, pq, h, ds)
        else:
            mul = mu * (ctx.l - ds / N if self.symmetric else ctx.l)
            diag = mul * self.mdiag + self.model.m_b * self.e_last
            dqf = jnp.concatenate([jnp.zeros((1, 3)), dq, jnp.zeros((1, 3))], axis=0)
            lin = (mul * self.msub)[:, None] * dqf[:-2] + diag[:, None] * dqf[1:-1] + (mul * self.msup)[:, None] * dqf[2:]
            lin = lin + ctx.C * ds + self.e_last[:, None] * self.body_term(ctx, F)[None, :]
        fs1, fq1, feta1 = self.end_forcing(ctx, h, ds, dq, c)  # f⁺ of the string forces and body loads (zeros without)
        hpq = lin - 0.5 * h * h * (gradV1[lay.nodes].reshape(N, 3) - fq1)
        hps = 0.0
        if self.reel:
            Q = self.forcing(ctx, ds, h, dq)
            hps = ctx.M0 * ds + jnp.sum(ctx.C * dq) - 0.5 * h * h * gradV1[0] + 0.5 * h * h * (Q + fs1)
            if self.symmetric:  # ∂C/∂Δs
                hps = hps + mu / 2.0 * ds * ds - mu / (6 * N) * self._quad(dq)
        hPi = jnp.zeros(3)
        if self.rigid:
            hPi = (vee(self.J_d @ F - F.T @ self.J_d)  # the matrix is skew: vee gives its axial vector
                   + self.model.m_b * jnp.cross(self.rho, F.T @ (ctx.R.T @ dq[-1]))
                   - 0.5 * h * h * (gradV1[lay.omega] - feta1))
        return self.join(hps, hpq, hPi)
