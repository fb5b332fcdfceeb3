"""Closed-form continuous-time equations of motion (models/README.md), hand-derived.

`ClosedFormEOM(model)` wraps a `StringPendulum` and evaluates the same equations as its
autodiff path (`mass_matrix`, `momentum`, `accelerations`, `ode_rhs`) without any
`jax.grad` / `jacfwd` / `jvp`. It reuses the model's parameters, its closed-form
`potential_gradient` and its forces (`reel_force`, `string_force`); no energy term is re-derived here except the
kinetic energy's derivatives, which are written out below.

Notation (nodes a = 1 … N+1, q_1 ≡ 0, v_a = q̇_a, v_1 = 0, ṡ = ṡ_p, l = (L − s_p)/N):

    D_a = q_a − q_{a+1},  Ḋ_a = v_a − v_{a+1}                       (elements a = 1 … N)
    C_b = c31_b D_b + c23_{b−1} D_{b−1}   (b = 2 … N+1; c31_{N+1} D_{N+1} ≡ 0)
    S(v)_b = (μl/6)(v_{b−1} + 4 v_b + v_{b+1}),  S(v)_{N+1} = (μl/6)(v_N + 2 v_{N+1})
    (`string.mass_model = "lumped"`, fixed length only: S(v)_b = μl v_b, S(v)_{N+1} = (μl/2) v_{N+1};
    the coefficients come from `models.model.STRING_MASS`)
    u = Rᵀ v_{N+1}

Mass matrix, w = (ṡ, v_2 … v_{N+1}, Ω):

    M_ss = M0 = μ s + κ_d + μ(L − s)/3,   M_{s,b} = C_bᵀ,   M_{b,b'} = string S ⊗ I3
    + m_b I3 on node N+1,   M_{N+1,Ω} = −m_b R ρ_c^,   M_ΩΩ = J_c − m_b ρ_c^ P ρ_c^ (P = RᵀR)

Force side F = ∂T/∂x − ∂V/∂x + Q − Ṁ w (and Π × Ω + M_R − (Ṁw)_Ω for Ω):

    s:   ⅓μ ṡ² − (μ/6N) Σ_a (|v_a|² + v_a·v_{a+1} + |v_{a+1}|²) − ∂V/∂s + Q_s
         − [⅔μ ṡ² + Σ_b Ċ_b·v_b]
    q_b: ṡ (G_b − G_{b−1}) − ∂V/∂q_b + Q_b − [−(ṡ/(N l)) S(v)_b + ṡ Ċ_b]
         − δ_{b,N+1} m_b R (Ω × (Ω × ρ_c)),   G_a = c31_a v_a + c23_a v_{a+1}, G_{N+1} ≡ 0
    Ω:   Π × Ω + m_b (Ω × ρ_c) × u + m_b ρ_c × (Ω × u) − ∂V/∂η,  Π = M_ΩΩ Ω + m_b ρ_c × u
         + m_b [c × P c − ρ_c × (Ṗ c)],  c = Ω × ρ_c,  Ṗ = P Ω^ − Ω^ P

P = RᵀR = I and M_ΩΩ = J_o for a rotation; the general-R terms are kept because the baselines'
R(quat) is not renormalised and `StringPendulum` (whose T_body is ½ m_b|v + R(Ω × ρ_c)|²
+ ½ Ω·J_c Ω) then differs from the J_o form at O(‖RᵀR − I‖). Keeping them makes the two
ODE right-hand sides agree for any quaternion, not only unit ones.

Solve (O(N)): the interior nodes 2 … N form a scalar tridiagonal block (μl/6)·tri(1, 4, 1)
whose pattern does not depend on the state, so it is factored once (at construction). The
"border" unknowns (s̈, q̈_{N+1}, Ω̇) — at most 7 — are found from a Schur complement, then
the interior accelerations by back substitution. With `tri_solve="lapack"` the interior solve
uses `jax.lax.linalg.tridiagonal_solve` (LAPACK gtsv on CPU); with "dense" it multiplies by the
precomputed inverse of tri(1, 4, 1) (O(N²), one small GEMM). "auto" picks dense up to 64
interior nodes (the two are within timing noise there) and lapack above (2× faster at N = 640).
"""

from __future__ import annotations

import functools

import numpy as np

from models._jax import jax, jnp
from models.model import StringPendulum, hat, quat_rate


class ClosedFormEOM:
    """Hand-derived M(x, R), p = M w and ẇ of a `StringPendulum` (same layout, same physics)."""

    def __init__(self, model: StringPendulum, tri_solve: str = "auto"):
        self.model = model
        self.layout = model.layout
        m = model
        self.N, self.mu, self.m_b, self.L = m.N, m.mu, m.m_b, m.L  # κ_d enters only through M0 (the model's)
        self.c31, self.c23 = np.asarray(m.c31), np.asarray(m.c23)
        self.rho_c, self.J_o, self.J_c = np.asarray(m.rho_c), np.asarray(m.J_o), np.asarray(m.J_c)
        self.rho_hat = np.array(hat(self.rho_c))
        n = self.N - 1  # interior free nodes 2..N
        self.n_int = n
        if tri_solve == "auto":
            tri_solve = "dense" if n <= 64 else "lapack"
        if tri_solve not in ("dense", "lapack"):
            raise ValueError(f"tri_solve must be 'auto', 'dense' or 'lapack', not {tri_solve!r}")
        self.tri_solve = tri_solve
        # string mass = (μl/den)·tri(o, 2d, o), last diagonal d (models.model.StringMass);
        # consistent: tri(1, 4, 1) and 2 below, lumped: diagonal
        sm = m.string_mass
        self.mass_den, self.mass_d, self.mass_o = sm.den, sm.d, sm.o
        if n > 0:
            tri = 2.0 * sm.d * np.eye(n) + sm.o * (np.eye(n, k=1) + np.eye(n, k=-1))
            self._tri_inv = np.linalg.inv(tri)
            #: z = o tri⁻¹ e_last (constant): the coupling of the interior to node N+1
            self._z = sm.o * self._tri_inv[:, -1]
            self._tri_dl = np.concatenate([[0.0], sm.o * np.ones(n - 1)])
            self._tri_d = 2.0 * sm.d * np.ones(n)
            self._tri_du = np.concatenate([sm.o * np.ones(n - 1), [0.0]])

    # ------------------------------------------------------------------------------------
    # Pieces
    # ------------------------------------------------------------------------------------
    def _split(self, x, w):
        m = self.model
        q = m.nodes(x)  # (N+1, 3), q_1 = 0
        v = m.node_velocities(w)  # (N+1, 3), v_1 = 0
        l = m.element_length(x)
        sd = m.reel_rate(w)
        return q, v, l, sd

    def _coupling(self, D):
        """C_b = c31_b D_b + c23_{b−1} D_{b−1}, b = 2 … N+1 (rows), from D_a, a = 1 … N."""
        tail = jnp.concatenate([self.c31[1:, None] * D[1:], jnp.zeros((1, 3))], axis=0)
        return self.c23[:, None] * D + tail

    def _string_apply_full(self, v, l):
        # v has N+1 rows; v[:-1] are nodes b−1 for b = 2..N+1, v[1:] the nodes themselves
        right = jnp.concatenate([v[2:], jnp.zeros((1, 3))], axis=0)
        d, o = self.mass_d, self.mass_o
        diag = jnp.asarray(np.concatenate([2.0 * d * np.ones(self.N - 1), [d]]))
        return (self.mu * l / self.mass_den) * (o * v[:-1] + diag[:, None] * v[1:] + o * right)

    def J_body(self, R):
        """M_ΩΩ = J_c − m_b ρ_c^ (RᵀR) ρ_c^ (= J_o when R is orthogonal; the ODE state's R(quat)
        is not renormalised, so this keeps the model's T_body exactly)."""
        rh = jnp.asarray(self.rho_hat)
        return jnp.asarray(self.J_c) - self.m_b * rh @ (R.T @ R) @ rh

    def M0(self, s):
        return self.model.reel_mass(s)  # the one definition (StringPendulum.reel_mass)

    # ------------------------------------------------------------------------------------
    # Legendre transform
    # ------------------------------------------------------------------------------------
    def momentum(self, x, R, w):
        """p = M(x, R) w, structured (O(N))."""
        lay = self.layout
        q, v, l, sd = self._split(x, w)
        pq = self._string_apply_full(v, l)
        pq = pq.at[-1].add(self.m_b * v[-1])
        parts = []
        if lay.has_reel:
            C = self._coupling(q[:-1] - q[1:])
            parts.append(jnp.atleast_1d(self.M0(x[0]) * sd + jnp.sum(C * v[1:])))
            pq = pq + sd * C
        if lay.has_attitude:
            om = w[lay.omega]
            pq = pq.at[-1].add(self.m_b * (R @ jnp.cross(om, self.rho_c)))
        parts.append(pq.ravel())
        if lay.has_attitude:
            parts.append(self.J_body(R) @ om + self.m_b * jnp.cross(self.rho_c, R.T @ v[-1]))
        return jnp.concatenate(parts)

    def mass_matrix(self, x, R):
        """M(x, R) assembled block-wise (dense nw × nw)."""
        lay, N = self.layout, self.N
        q, l = self.model.nodes(x), self.model.element_length(x)
        d, o = self.mass_d, self.mass_o
        tri = (2.0 * d * np.eye(N) + o * (np.eye(N, k=1) + np.eye(N, k=-1)))
        tri[-1, -1] = d
        K = (self.mu * l / self.mass_den) * jnp.asarray(tri)
        K = K.at[-1, -1].add(self.m_b)
        Mqq = jnp.kron(K, jnp.eye(3))
        r = lay.n_reel
        M = jnp.zeros((lay.nw, lay.nw))
        M = M.at[lay.nodes, lay.nodes].set(Mqq)
        if lay.has_reel:
            C = self._coupling(q[:-1] - q[1:]).ravel()
            M = M.at[0, 0].set(self.M0(x[0]))
            M = M.at[0, lay.nodes].set(C).at[lay.nodes, 0].set(C)
        if lay.has_attitude:
            B = -self.m_b * R @ jnp.asarray(self.rho_hat)  # M_{q_{N+1}, Ω}
            tip = slice(r + 3 * N - 3, r + 3 * N)
            M = M.at[tip, lay.omega].set(B).at[lay.omega, tip].set(B.T)
            M = M.at[lay.omega, lay.omega].set(self.J_body(R))
        return M

    # ------------------------------------------------------------------------------------
    # Force side
    # ------------------------------------------------------------------------------------
    def force(self, t, x, R, w):
        """F = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w (so that M ẇ = F)."""
        m, lay = self.model, self.layout
        q, v, l, sd = self._split(x, w)
        dV = m.potential_gradient(x, R)
        Fq = -dV[lay.nodes].reshape(self.N, 3)
        parts = []
        if lay.has_reel:
            mu, N = self.mu, self.N
            va, vb = v[:-1], v[1:]
            quad = jnp.sum(va * va + va * vb + vb * vb)
            Cdot = self._coupling(va - vb)
            Fs = (mu / 3.0 - 2.0 * mu / 3.0) * sd * sd - mu / (6.0 * N) * quad - jnp.sum(Cdot * v[1:])
            Fs = Fs - dV[0] + m.reel_force(t, x, w)
            parts.append(jnp.atleast_1d(Fs))
            G = self.c31[:, None] * va + self.c23[:, None] * vb  # a = 1..N
            dTdq = jnp.concatenate([G[1:], jnp.zeros((1, 3))], axis=0) - G
            Fq = Fq + sd * (dTdq - Cdot) + (sd / (N * l)) * self._string_apply_full(v, l)
        if lay.has_attitude:
            om = w[lay.omega]
            rho = self.rho_c
            u = R.T @ v[-1]
            Fq = Fq.at[-1].add(-self.m_b * (R @ jnp.cross(om, jnp.cross(om, rho))))
            Pi = self.J_body(R) @ om + self.m_b * jnp.cross(rho, u)
            c = jnp.cross(om, rho)
            F_om = (jnp.cross(Pi, om) + self.m_b * jnp.cross(c, u)
                    + self.m_b * jnp.cross(rho, jnp.cross(om, u)) - dV[lay.omega])
            # terms that vanish for orthogonal R (P = RᵀR = I): M_R and Ṁ w of ½ m_b cᵀ P c
            P = R.T @ R
            Om = hat(om)
            Pdot = P @ Om - Om @ P
            F_om = F_om + self.m_b * (jnp.cross(c, P @ c) - jnp.cross(rho, Pdot @ c))
        parts.append(Fq.ravel())
        if lay.has_attitude:
            parts.append(F_om)
        F = jnp.concatenate(parts)
        if m.string_forces:
            F = F + m.string_force(t, x, w)
        return F

    # ------------------------------------------------------------------------------------
    # Structured solve of M a = F
    # ------------------------------------------------------------------------------------
    def _tri_inv_apply(self, B):
        """tri(1,4,1)⁻¹ B for B of shape (n, k)."""
        if self.tri_solve == "dense":
            return jnp.asarray(self._tri_inv) @ B
        k = B.shape[1]
        return jax.lax.linalg.tridiagonal_solve(
            jnp.asarray(self._tri_dl), jnp.asarray(self._tri_d), jnp.asarray(self._tri_du), B
        ) if k else B

    def solve(self, x, R, F):
        """a = M(x, R)⁻¹ F by a Schur complement on (s̈, q̈_{N+1}, Ω̇); O(N) with 'lapack'."""
        lay, N, n = self.layout, self.N, self.n_int
        q, l = self.model.nodes(x), self.model.element_length(x)
        h = self.mu * l / self.mass_den  # interior block is h·tri(o, 2d, o) (h·tri(1,4,1) consistent)
        d, o = self.mass_d, self.mass_o
        Fq = F[lay.nodes].reshape(N, 3)
        r_int, r_L = Fq[:-1], Fq[-1]
        has_s, has_b = lay.has_reel, lay.has_attitude
        C = self._coupling(q[:-1] - q[1:]) if has_s else None
        # interior: A = (1/h) tri⁻¹ (r_int − C_int a_s) − z a_L
        if n > 0:
            rhs_cols = [r_int] + ([C[:-1]] if has_s else [])
            Z = self._tri_inv_apply(jnp.concatenate(rhs_cols, axis=1)) / h
            Zr = Z[:, :3]
            ZC = Z[:, 3:6] if has_s else None
            z = jnp.asarray(self._z)
        # border system on u = (a_s, a_L, α)
        I3 = jnp.eye(3)
        dL = d * h + self.m_b - (o * h * z[-1] if n > 0 else 0.0)
        rows, rhs = [], []
        # row for a_L
        blk_L = []
        if has_s:
            cL = C[-1] - (o * h * ZC[-1] if n > 0 else 0.0)
            blk_L.append(cL[:, None])
        blk_L.append(dL * I3)
        if has_b:
            blk_L.append(-self.m_b * R @ jnp.asarray(self.rho_hat))
        rows.append(jnp.concatenate(blk_L, axis=1))
        rhs.append(r_L - (o * h * Zr[-1] if n > 0 else 0.0))
        if has_s:
            Ci = C[:-1]
            ss = self.M0(x[0]) - (jnp.sum(Ci * ZC) if n > 0 else 0.0)
            sL = C[-1] - (z @ Ci if n > 0 else 0.0)
            row_s = [jnp.atleast_2d(ss), sL[None, :]] + ([jnp.zeros((1, 3))] if has_b else [])
            rows.insert(0, jnp.concatenate(row_s, axis=1))
            rhs.insert(0, jnp.atleast_1d(F[0] - (jnp.sum(Ci * Zr) if n > 0 else 0.0)))
        if has_b:
            row_b = ([jnp.zeros((3, 1))] if has_s else []) + [
                self.m_b * jnp.asarray(self.rho_hat) @ R.T, self.J_body(R)]
            rows.append(jnp.concatenate(row_b, axis=1))
            rhs.append(F[lay.omega])
        Mb = jnp.concatenate(rows, axis=0)
        ub = jnp.linalg.solve(Mb, jnp.concatenate(rhs))
        i = 0
        parts = []
        if has_s:
            a_s = ub[0]
            parts.append(ub[:1])
            i = 1
        a_L = ub[i:i + 3]
        if n > 0:
            A = Zr - z[:, None] * a_L[None, :]
            if has_s:
                A = A - ZC * a_s
            parts.append(A.ravel())
        parts.append(a_L)
        if has_b:
            parts.append(ub[i + 3:i + 6])
        return jnp.concatenate(parts)

    def accelerations(self, t, x, R, w):
        """ẇ from M ẇ = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w, closed form, O(N) structured solve."""
        return self.solve(x, R, self.force(t, x, R, w))

    def accelerations_dense(self, t, x, R, w):
        """Same, with a dense solve of the closed-form M (reference for the structured solve)."""
        return jnp.linalg.solve(self.mass_matrix(x, R), self.force(t, x, R, w))

    def velocity_from_momentum(self, x, R, p):
        """w = M⁻¹ p by the structured solve."""
        return self.solve(x, R, p)

    # ------------------------------------------------------------------------------------
    # Quaternion ODE state (same layout and semantics as StringPendulum.ode_rhs)
    # ------------------------------------------------------------------------------------
    def ode_rhs(self, t, y):
        m, lay = self.model, self.layout
        x, R, w, _ = m.split_state(y)
        parts = [w[: lay.nx]]
        if lay.has_attitude:
            parts.append(quat_rate(y[lay.y_quat], w[lay.omega]))
        parts.append(self.accelerations(t, x, R, w))
        if lay.has_work:
            parts.append(jnp.atleast_1d(m.power(t, x, w)))
        return jnp.concatenate(parts)

    @functools.cached_property
    def ode_rhs_jit(self):
        return jax.jit(self.ode_rhs)


@functools.lru_cache(maxsize=64)
def build_closed_form(scene) -> ClosedFormEOM:
    """The closed-form equations of a scene (cached like `models.build_model`)."""
    from models.model import build_model

    return ClosedFormEOM(build_model(scene))
