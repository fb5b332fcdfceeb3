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
    u = Rᵀ v_{N+1},  c = Ω × ρ_c,  W = R ρ_c^  (so R(Ω × ρ_c) = R c and ρ_c^ P ρ_c^ = −WᵀW)

Mass matrix, w = (ṡ, v_2 … v_{N+1}, Ω):

    M_ss = M0 = μ s + κ_d + μ(L − s)/3,   M_{s,b} = C_bᵀ,   M_{b,b'} = string S ⊗ I3
    + m_b I3 on node N+1,   M_{N+1,Ω} = −m_b W,   M_ΩΩ = J_c − m_b ρ_c^ P ρ_c^ = J_c + m_b WᵀW (P = RᵀR)

Force side F = ∂T/∂x − ∂V/∂x + Q − Ṁ w (and Π × Ω + M_R − (Ṁw)_Ω for Ω):

    s:   ⅓μ ṡ² − (μ/6N) Σ_a (|v_a|² + v_a·v_{a+1} + |v_{a+1}|²) − ∂V/∂s + Q_s
         − [⅔μ ṡ² + Σ_b Ċ_b·v_b]
    q_b: ṡ (G_b − G_{b−1}) − ∂V/∂q_b + Q_b − [−(ṡ/(N l)) S(v)_b + ṡ Ċ_b]
         − δ_{b,N+1} m_b R (Ω × (Ω × ρ_c)),   G_a = c31_a v_a + c23_a v_{a+1}, G_{N+1} ≡ 0
    Ω:   Π × Ω + m_b (Ω × ρ_c) × u + m_b ρ_c × (Ω × u) − ∂V/∂η,  Π = M_ΩΩ Ω + m_b ρ_c × u
         + m_b [c × P c − ρ_c × (Ṗ c)],  c = Ω × ρ_c,  Ṗ c = P (Ω × c) − Ω × (P c)

P = RᵀR = I and M_ΩΩ = J_o for a rotation; the general-R terms are kept because the baselines'
R(quat) is not renormalised and `StringPendulum` (whose T_body is ½ m_b|v + R(Ω × ρ_c)|²
+ ½ Ω·J_c Ω) then differs from the J_o form at O(‖RᵀR − I‖). Keeping them makes the two
ODE right-hand sides agree for any quaternion, not only unit ones.

Solve (O(N)): the interior nodes 2 … N form a scalar tridiagonal block h·T, h = μl/6,
T = tri(1, 4, 1), whose pattern does not depend on the state, so it is factored once (at
construction). The "border" unknowns (s̈, q̈_{N+1}, Ω̇) — at most 7 — are found from their
Schur complement by block elimination (`_border_solve`), then the interior accelerations by
back substitution.

Why it is written this way (speed): XLA on CPU compiles a small loop (an integrator's step
loop with this right-hand side inside) into one native function only when the loop contains
no library call (`models._jax`; XLA's small-while-loop hoisting skips loops with custom
calls), and a LAPACK solve is one. So nothing here calls LAPACK: the ≤ 7 border unknowns are
eliminated by hand on their 3×3 blocks (the node-(N+1) block is a multiple of the identity,
which leaves one 3×3 SPD system for Ω̇, solved by its adjugate), 3×3 algebra is written as
broadcast products (no tiny dots), and the interior solve is either a product with the
precomputed inverse of T (`tri_solve="dense"`) or a Thomas sweep with the constant factors
precomputed (`"thomas"`, two `lax.scan`s). "auto" picks dense up to `DENSE_MAX_INTERIOR`
interior nodes and Thomas above.
"""

from __future__ import annotations

import functools

import numpy as np

from models._jax import jax, jnp
from models.model import StringPendulum, hat, quat_rate

#: Largest interior size for which `tri_solve="auto"` multiplies by the dense inverse of T
#: (an n×n matrix–vector product, O(n²)) instead of the two O(n) Thomas sweeps (sequential
#: loops): measured in a compiled loop on one core, dense wins up to about this size.
DENSE_MAX_INTERIOR = 24

TRI_SOLVERS = ("auto", "dense", "thomas")


# ----------------------------------------------------------------------------------------
# Small vector algebra on (…, 3) arrays, written as broadcast products (no dot ops)
# ----------------------------------------------------------------------------------------
def _cross(a, b):
    """a × b for 3-vectors."""
    return jnp.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _matvec(M, v):
    """M v for a 3×3 M."""
    return jnp.sum(M * v[None, :], axis=1)


def _rmatvec(M, v):
    """Mᵀ v for a 3×3 M."""
    return jnp.sum(M * v[:, None], axis=0)


def _matmul(A, B):
    """A B for 3×3 matrices."""
    return jnp.sum(A[:, :, None] * B[None, :, :], axis=1)


def _gram(W):
    """Wᵀ W for a 3×3 W (symmetric by construction)."""
    return jnp.sum(W[:, :, None] * W[:, None, :], axis=0)


def _solve_spd3(K, g):
    """K⁻¹ g for a symmetric positive definite 3×3 K, by its adjugate (upper triangle read)."""
    k00, k01, k02, k11, k12, k22 = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2], K[2, 2]
    a00 = k11 * k22 - k12 * k12
    a01 = k02 * k12 - k01 * k22
    a02 = k01 * k12 - k02 * k11
    a11 = k00 * k22 - k02 * k02
    a12 = k01 * k02 - k00 * k12
    a22 = k00 * k11 - k01 * k01
    det = k00 * a00 + k01 * a01 + k02 * a02
    return jnp.stack([a00 * g[0] + a01 * g[1] + a02 * g[2],
                      a01 * g[0] + a11 * g[1] + a12 * g[2],
                      a02 * g[0] + a12 * g[1] + a22 * g[2]]) / det


def _prev(a):
    """Rows shifted down by one: row b holds a_{b−1} (zeros in the first row)."""
    return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]], axis=0)


def _next(a):
    """Rows shifted up by one: row b holds a_{b+1} (zeros in the last row)."""
    return jnp.concatenate([a[1:], jnp.zeros_like(a[:1])], axis=0)


def thomas_factors(diag: float, off: float, n: int):
    """Constant factors of the Thomas algorithm for tri(off, diag, off) of size n (numpy):
    (1/pivot_i, upper_i), pivot_0 = diag, pivot_i = diag − off·upper_{i−1}, upper_i = off/pivot_i."""
    inv_pivot, upper = np.zeros(n), np.zeros(n)
    pivot = diag
    for i in range(n):
        if i:
            pivot = diag - off * upper[i - 1]
        inv_pivot[i] = 1.0 / pivot
        upper[i] = off / pivot
    return inv_pivot, upper


def thomas_solve(off: float, inv_pivot, upper, B):
    """tri(off, diag, off)⁻¹ B for B of shape (n, k), with the factors of `thomas_factors`:
    forward y_i = (B_i − off·y_{i−1})/pivot_i, backward X_i = y_i − upper_i X_{i+1}."""

    def forward(y_prev, row):
        b, ip = row
        y = (b - off * y_prev) * ip
        return y, y

    def backward(x_next, row):
        y, u = row
        x = y - u * x_next
        return x, x

    zero = jnp.zeros(B.shape[1:], dtype=B.dtype)
    _, Y = jax.lax.scan(forward, zero, (B, jnp.asarray(inv_pivot)))
    _, X = jax.lax.scan(backward, zero, (Y, jnp.asarray(upper)), reverse=True)
    return X


class ClosedFormEOM:
    """Hand-derived M(x, R), p = M w and ẇ of a `StringPendulum` (same layout, same physics)."""

    def __init__(self, model: StringPendulum, tri_solve: str = "auto"):
        if tri_solve not in TRI_SOLVERS:
            raise ValueError(f"tri_solve = {tri_solve!r} is invalid (allowed: {', '.join(map(repr, TRI_SOLVERS))})")
        self.model = model
        self.layout = model.layout
        m = model
        self.N, self.mu, self.m_b, self.L = m.N, m.mu, m.m_b, m.L  # κ_d enters only through M0 (the model's)
        self.c31, self.c23 = np.asarray(m.c31), np.asarray(m.c23)
        #: c31_{b} for the rows b = 2 … N+1 of C (c31_{N+1} D_{N+1} ≡ 0)
        self._c31_next = np.concatenate([self.c31[1:], [0.0]])
        self.rho_c, self.J_o, self.J_c = np.asarray(m.rho_c), np.asarray(m.J_o), np.asarray(m.J_c)
        self.rho_hat = np.array(hat(self.rho_c))
        n = self.N - 1  # interior free nodes 2..N
        self.n_int = n
        if tri_solve == "auto":
            tri_solve = "dense" if n <= DENSE_MAX_INTERIOR else "thomas"
        self.tri_solve = tri_solve
        # string mass = (μl/den)·tri(o, 2d, o), last diagonal d (models.model.StringMass);
        # consistent: tri(1, 4, 1) and 2 below, lumped: diagonal
        sm = m.string_mass
        self.mass_den, self.mass_d, self.mass_o = sm.den, sm.d, sm.o
        #: diagonal of the string mass over nodes 2 … N+1, in units of μl/den
        self._mass_diag = np.concatenate([2.0 * sm.d * np.ones(n), [sm.d]])
        #: node N+1's diagonal after eliminating the interior, in units of μl/den: d − o z_last
        self._tip_diag = float(sm.d)
        if n > 0:
            self._inv_pivot, self._upper = thomas_factors(2.0 * sm.d, sm.o, n)
            tri = 2.0 * sm.d * np.eye(n) + sm.o * (np.eye(n, k=1) + np.eye(n, k=-1))
            self._tri_inv = np.linalg.inv(tri) if tri_solve == "dense" else None
            #: z = o T⁻¹ e_last (constant): the coupling of the interior to node N+1
            e_last = np.zeros((n, 1))
            e_last[-1] = 1.0
            self._z = sm.o * np.asarray(self._thomas_numpy(e_last))[:, 0]
            self._tip_diag = float(sm.d - sm.o * self._z[-1])

    def _thomas_numpy(self, B):
        off, ip, up = self.mass_o, self._inv_pivot, self._upper
        Y = np.zeros_like(B)
        for i in range(len(B)):
            Y[i] = (B[i] - (off * Y[i - 1] if i else 0.0)) * ip[i]
        for i in range(len(B) - 2, -1, -1):
            Y[i] -= up[i] * Y[i + 1]
        return Y

    # ------------------------------------------------------------------------------------
    # Pieces
    # ------------------------------------------------------------------------------------
    def _nodes(self, x):
        """q_2 … q_{N+1} as (N, 3)."""
        return x[self.layout.nodes].reshape(self.N, 3)

    def _velocities(self, w):
        """v_2 … v_{N+1} as (N, 3)."""
        return w[self.layout.nodes].reshape(self.N, 3)

    def _coupling(self, D):
        """C_b = c31_b D_b + c23_{b−1} D_{b−1}, rows b = 2 … N+1, from D_a, rows a = 1 … N."""
        return self.c23[:, None] * D + self._c31_next[:, None] * _next(D)

    def _string_apply(self, vn, l):
        """S(v)_b = (μl/den)(o v_{b−1} + diag_b v_b + o v_{b+1}), rows b = 2 … N+1 (v_1 = 0)."""
        o = self.mass_o
        inner = self._mass_diag[:, None] * vn
        if o:
            inner = inner + o * (_prev(vn) + _next(vn))
        return (self.mu * l / self.mass_den) * inner

    def _body_frame(self, R):
        """W = R ρ_c^ (M_{N+1,Ω} = −m_b W; R(Ω × ρ_c) = −W Ω)."""
        return _matmul(R, jnp.asarray(self.rho_hat))

    def J_body(self, R):
        """M_ΩΩ = J_c − m_b ρ_c^ (RᵀR) ρ_c^ = J_c + m_b WᵀW (= J_o when R is orthogonal; the
        ODE state's R(quat) is not renormalised, so this keeps the model's T_body exactly)."""
        return jnp.asarray(self.J_c) + self.m_b * _gram(self._body_frame(R))

    def M0(self, s):
        return self.model.reel_mass(s)  # the one definition (StringPendulum.reel_mass)

    def _join(self, s, nodes, omega):
        """A vector over w's layout from its parts (s: scalar or None, nodes (N, 3), omega or None)."""
        parts = ([jnp.reshape(s, (1,))] if self.layout.has_reel else []) + [nodes.reshape(-1)]
        if self.layout.has_attitude:
            parts.append(omega)
        return jnp.concatenate(parts)

    def _parts(self, vec):
        """(s part or None, node part (N, 3), Ω part or None) of a vector over w's layout."""
        lay = self.layout
        s = vec[0] if lay.has_reel else None
        om = vec[lay.omega] if lay.has_attitude else None
        return s, vec[lay.nodes].reshape(self.N, 3), om

    # ------------------------------------------------------------------------------------
    # Legendre transform
    # ------------------------------------------------------------------------------------
    def momentum(self, x, R, w):
        """p = M(x, R) w, structured (O(N)):
        p_s = M0 ṡ + Σ_b C_b·v_b,  p_b = S(v)_b + ṡ C_b (+ m_b (v_{N+1} + R c) on node N+1),
        p_Ω = M_ΩΩ Ω + m_b ρ_c × u."""
        lay = self.layout
        qn, vn, l = self._nodes(x), self._velocities(w), self.model.element_length(x)
        pq = self._string_apply(vn, l)
        tip = self.m_b * vn[-1]
        p_s = p_om = None
        if lay.has_attitude:
            om = w[lay.omega]
            Rc = _matvec(R, _cross(om, jnp.asarray(self.rho_c)))
            tip = tip + self.m_b * Rc
            rho = jnp.asarray(self.rho_c)
            p_om = (_matvec(jnp.asarray(self.J_c), om) + self.m_b * _cross(rho, _rmatvec(R, Rc))
                    + self.m_b * _cross(rho, _rmatvec(R, vn[-1])))
        if lay.has_reel:
            sd = w[0]
            C = self._coupling(_prev(qn) - qn)
            p_s = self.M0(x[0]) * sd + jnp.sum(C * vn)
            pq = pq + sd * C
        pq = pq.at[-1].add(tip)
        return self._join(p_s, pq, p_om)

    def mass_matrix(self, x, R):
        """M(x, R) assembled block-wise (dense nw × nw; a reference for the structured solve)."""
        lay, N = self.layout, self.N
        q, l = self._nodes(x), self.model.element_length(x)
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
            C = self._coupling(_prev(q) - q).ravel()
            M = M.at[0, 0].set(self.M0(x[0]))
            M = M.at[0, lay.nodes].set(C).at[lay.nodes, 0].set(C)
        if lay.has_attitude:
            B = -self.m_b * self._body_frame(R)  # M_{q_{N+1}, Ω}
            tip = slice(r + 3 * N - 3, r + 3 * N)
            M = M.at[tip, lay.omega].set(B).at[lay.omega, tip].set(B.T)
            M = M.at[lay.omega, lay.omega].set(self.J_body(R))
        return M

    # ------------------------------------------------------------------------------------
    # Force side
    # ------------------------------------------------------------------------------------
    def _force_parts(self, t, x, R, w):
        """(F_s or None, F_q (N, 3), F_Ω or None) of F = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w."""
        m, lay = self.model, self.layout
        qn, vn, l = self._nodes(x), self._velocities(w), m.element_length(x)
        dV_s, dV_q, dV_om = self._parts(m.potential_gradient(x, R))
        Fq = -dV_q
        Fs = F_om = None
        if lay.has_reel:
            mu, N, sd = self.mu, self.N, w[0]
            va = _prev(vn)
            quad = jnp.sum(va * va + va * vn + vn * vn)
            Cdot = self._coupling(va - vn)
            Fs = (mu / 3.0 - 2.0 * mu / 3.0) * sd * sd - mu / (6.0 * N) * quad - jnp.sum(Cdot * vn)
            Fs = Fs - dV_s + m.reel_force(t, x, w)
            G = self.c31[:, None] * va + self.c23[:, None] * vn  # a = 1..N
            Fq = Fq + sd * (_next(G) - G - Cdot) + (sd / (N * l)) * self._string_apply(vn, l)
        if lay.has_attitude:
            mb, om = self.m_b, w[lay.omega]
            rho = jnp.asarray(self.rho_c)
            c = _cross(om, rho)
            Rc = _matvec(R, c)
            Pc = _rmatvec(R, Rc)
            u = _rmatvec(R, vn[-1])
            R_om_c = _matvec(R, _cross(om, c))
            Fq = Fq.at[-1].add(-mb * R_om_c)
            Pi = _matvec(jnp.asarray(self.J_c), om) + mb * _cross(rho, Pc) + mb * _cross(rho, u)
            Pdot_c = _rmatvec(R, R_om_c) - _cross(om, Pc)
            F_om = (_cross(Pi, om) + mb * _cross(c, u) + mb * _cross(rho, _cross(om, u)) - dV_om
                    # terms that vanish for orthogonal R (P = RᵀR = I): M_R and Ṁ w of ½ m_b cᵀ P c
                    + mb * (_cross(c, Pc) - _cross(rho, Pdot_c)))
        if m.string_forces:
            Q_s, Q_q, _ = self._parts(m.string_force(t, x, w))
            Fq = Fq + Q_q
            if lay.has_reel:
                Fs = Fs + Q_s
        return Fs, Fq, F_om

    def force(self, t, x, R, w):
        """F = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w (so that M ẇ = F), over w's layout."""
        return self._join(*self._force_parts(t, x, R, w))

    # ------------------------------------------------------------------------------------
    # Structured solve of M a = F
    # ------------------------------------------------------------------------------------
    def _tri_inv_apply(self, B):
        """T⁻¹ B for B of shape (n, k), T = tri(o, 2d, o)."""
        if self.tri_solve == "dense":
            return jnp.sum(jnp.asarray(self._tri_inv)[:, :, None] * B[None, :, :], axis=1)
        return thomas_solve(self.mass_o, self._inv_pivot, self._upper, B)

    def _border_solve(self, R, dL, f_L, s_block, f_om):
        """(a_s, a_L, α) of the border system left after eliminating the interior,

            [σ0  cᵀ    0  ] [a_s]   [f_s]
            [c   dL I  B  ] [a_L] = [f_L],   B = −m_b W,
            [0   Bᵀ    Jb ] [α  ]   [f_Ω]

        (rows and columns of absent unknowns dropped; s_block = (σ0, c, f_s) or None). a_L is
        eliminated first (its block is a multiple of I), then a_s, leaving one 3×3 SPD system
        K' α = g' with K = Jb − BᵀB/dL = J_c + m_b (1 − m_b/dL) WᵀW."""
        inv_dL = 1.0 / dL
        a_s = alpha = None
        if s_block is not None:
            sigma0, cL, f_s = s_block
            sigma = sigma0 - inv_dL * jnp.sum(cL * cL)
            g_s = f_s - inv_dL * jnp.sum(cL * f_L)
        if f_om is not None:
            mb = self.m_b
            W = self._body_frame(R)
            K = jnp.asarray(self.J_c) + (mb * (1.0 - mb * inv_dL)) * _gram(W)
            g = f_om + (mb * inv_dL) * _rmatvec(W, f_L)
            if s_block is not None:
                beta = (mb * inv_dL) * _rmatvec(W, cL)
                K = K - beta[:, None] * beta[None, :] / sigma
                g = g - beta * (g_s / sigma)
            alpha = _solve_spd3(K, g)
            rhs_L = f_L + mb * _matvec(W, alpha)
            if s_block is not None:
                a_s = (g_s - jnp.sum(beta * alpha)) / sigma
        else:
            rhs_L = f_L
            if s_block is not None:
                a_s = g_s / sigma
        if a_s is not None:
            rhs_L = rhs_L - cL * a_s
        return a_s, inv_dL * rhs_L, alpha

    def _solve_parts(self, x, R, Fs, Fq, F_om):
        """(a_s, a_q (N, 3), α) of M a = F: interior by T⁻¹, border by `_border_solve`.

        Interior rows: h T A + o h e_last a_Lᵀ + C_int a_s = r_int, h = μl/den, so
        A = Zr − z a_Lᵀ − ZC a_s with Zr = T⁻¹ r_int / h, ZC = T⁻¹ C_int / h, z = o T⁻¹ e_last."""
        lay, n = self.layout, self.n_int
        h = self.mu * self.model.element_length(x) / self.mass_den
        o = self.mass_o
        has_s = lay.has_reel
        C = self._coupling(_prev(self._nodes(x)) - self._nodes(x)) if has_s else None
        r_L, s_block = Fq[-1], None
        dL = h * self._tip_diag + self.m_b
        if n > 0:
            cols = jnp.concatenate([Fq[:-1], C[:-1]], axis=1) if has_s else Fq[:-1]
            Z = self._tri_inv_apply(cols) * (1.0 / h)
            Zr = Z[:, :3]
            f_L = r_L - (o * h) * Zr[-1]
            if has_s:
                Ci, ZC = C[:-1], Z[:, 3:]
                cL = C[-1] - (o * h) * ZC[-1]
                s_block = (self.M0(x[0]) - jnp.sum(Ci * ZC), cL, Fs - jnp.sum(Ci * Zr))
        else:
            f_L = r_L
            if has_s:
                s_block = (self.M0(x[0]), C[-1], Fs)
        a_s, a_L, alpha = self._border_solve(R, dL, f_L, s_block, F_om)
        if n > 0:
            A = Zr - jnp.asarray(self._z)[:, None] * a_L[None, :]
            if has_s:
                A = A - ZC * a_s
            a_q = jnp.concatenate([A, a_L[None, :]], axis=0)
        else:
            a_q = a_L[None, :]
        return a_s, a_q, alpha

    def solve(self, x, R, F):
        """a = M(x, R)⁻¹ F by a Schur complement on (s̈, q̈_{N+1}, Ω̇), O(N)."""
        return self._join(*self._solve_parts(x, R, *self._parts(F)))

    def accelerations(self, t, x, R, w):
        """ẇ from M ẇ = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w, closed form, O(N) structured solve."""
        return self._join(*self._solve_parts(x, R, *self._force_parts(t, x, R, w)))

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
