"""Closed-form continuous-time equations of motion (models/README.md), hand-derived.

`ClosedFormEOM(model)` wraps a `StringPendulum` and evaluates the same equations as its
autodiff path (`mass_matrix`, `momentum`, `accelerations`, `ode_rhs`) without any
`jax.grad` / `jacfwd` / `jvp`. It reuses the model's parameters, its closed-form
`potential_gradient` and its forces (`reel_force`, `string_force`, `body_load`); no energy term is re-derived here except the
kinetic energy's derivatives, which are written out below.

Notation (nodes a = 1 … N+1, q_1 ≡ 0, v_a = q̇_a, v_1 = 0, ṡ = ṡ_p, l = (L − s_p)/N):

    D_a = q_a − q_{a+1},  Ḋ_a = v_a − v_{a+1}                       (elements a = 1 … N)
    C_b = c31_b D_b + c23_{b−1} D_{b−1}   (b = 2 … N+1; c31_{N+1} D_{N+1} ≡ 0)
    S(v)_b = (μl/6)(v_{b−1} + 4 v_b + v_{b+1}),  S(v)_{N+1} = (μl/6)(v_N + 2 v_{N+1})
    (`string.mass_model = "lumped"`, fixed length only: S(v)_b = μl v_b, S(v)_{N+1} = (μl/2) v_{N+1};
    the coefficients come from `models.model.STRING_MASS`)
    u = Rᵀ v_{N+1},  c = Ω × ρ_c,  W = R ρ_c^  (so ρ_c^ P ρ_c^ = −WᵀW)

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

Solve (O(N)): the interior nodes 2 … N form the block h·T ⊗ I3, h = μl/den, T = tri(o, 2d, o)
(tri(1, 4, 1) for the consistent mass), which does not depend on the state, so its factors
are computed once (`ToeplitzTridiagonal`). The "border" unknowns (s̈, q̈_{N+1}, Ω̇) — at most
7 — are found first, from their Schur complement (whose coefficients need only the constant
z = o T⁻¹ e_last and, with a reel, T⁻¹ C), by block elimination (`_border_solve`); then the
interior accelerations by one solve with T (`_solve_parts`).

How it is written, and why (speed). XLA on CPU compiles an integrator's step loop with this
right-hand side inside into one native function only when the loop holds no library call
(`models._jax`; XLA's small-while-loop hoisting skips loops with custom calls), and it
compiles a fused `concatenate` (or `pad`) into a branch per element, which costs more than
the arithmetic. So, measured in a compiled loop:

* no LAPACK: the ≤ 7 border unknowns are eliminated by hand on their 3×3 blocks (node N+1's
  block is a multiple of I3, which leaves one 3×3 SPD system for Ω̇, solved by its adjugate);
* node quantities are flat node-major vectors (3N,) (rows b = 2 … N+1 of three components):
  a neighbour is a shift by 3 elements, written with `dynamic_update_slice` (an in-place
  update of a contiguous range) rather than concatenation; outputs are written into one
  buffer the same way (`_assemble`);
* the interior solve is not a sequential sweep (a Thomas loop in `lax.scan` costs 6–9 ns
  per node per sweep): T is a Toeplitz tridiagonal matrix, T = (o/r)[(I + rS)(I + rSᵀ)
  + r² e₁e₁ᵀ] (S the down-shift, r + 1/r = 2d/o), so T⁻¹ is a Sherman–Morrison correction
  of the first row and two constant-coefficient bidiagonal solves, each a first-order linear
  recurrence evaluated by recursive doubling (5 shifted vector updates, exact to round-off);
* per-node values broadcast over three components (z_i a_L, …) are avoided in N-long
  loops (XLA divides the flat index by 3 for each element there): the interior is solved for
  its final right-hand side, so its last update is the result;
* 3×3 algebra is written as broadcast products (no tiny dot ops).

Measured (fixed_length, in a compiled loop, one core of a shared machine at load ~7, against
a numba implementation of the same equations timed in the same run): 0.34 µs per evaluation
at N = 10 and 3.1 µs at N = 160 (numba 0.59 and 4.4 µs); the version with LAPACK solves and
concatenations took 3.9 and 13 µs.
"""

from __future__ import annotations

import functools

import numpy as np

from reelbench.models._jax import jax, jnp
from reelbench.models.model import StringPendulum, hat, quat_rate

TRI_SOLVERS = ("auto", "doubling", "dense")

#: Recursive doubling stops once the terms it would still add are below this fraction of the
#: right-hand side's magnitude (≈ 1/200 of an ulp): the result is then exact to round-off.
DOUBLING_TAIL = 2.0**-60


# ----------------------------------------------------------------------------------------
# 3-vector and 3×3 algebra, written as broadcast products (no dot ops)
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


# ----------------------------------------------------------------------------------------
# Flat node vectors (3N,): rows b = 2 … N+1, three components each
# ----------------------------------------------------------------------------------------
def _put(buf, part, start: int):
    """buf with part written at buf[start : start + len(part)] (XLA updates in place)."""
    return jax.lax.dynamic_update_slice(buf, part, (start,))


def _assemble(size: int, *placed):
    """A vector of `size` from (start, part) pairs (zeros elsewhere)."""
    out = jnp.zeros(size)
    for start, part in placed:
        out = _put(out, part, start)
    return out


def _from_prev(f, width: int = 3):
    """Row b holds f's row b − 1 (zeros in the first row); rows are `width` long."""
    return _put(jnp.zeros_like(f), f[:-width], width)


def _from_next(f, width: int = 3):
    """Row b holds f's row b + 1 (zeros in the last row)."""
    return _put(jnp.zeros_like(f), f[width:], 0)


def _rows_dot(weights, f, k: int = 3):
    """Σ_i weights_i f_i over the rows of f flat (n·k,): a k-vector (weights a numpy (n,))."""
    n = len(weights)
    return jnp.sum(jnp.asarray(weights)[:, None] * f.reshape(n, k), axis=0)


def _per_node(values):
    """A per-node constant (one value per row) spread over the row's three components (numpy)."""
    return np.repeat(np.asarray(values, dtype=float), 3)


# ----------------------------------------------------------------------------------------
# The interior solve: T = tri(off, diag, off), Toeplitz
# ----------------------------------------------------------------------------------------
class ToeplitzTridiagonal:
    """scale·T⁻¹B for the constant n×n matrix T = tri(off, diag, off), B flat (n·k,) in rows of k.

    With S the down-shift and r + 1/r = diag/off (|r| < 1, T diagonally dominant):

        T = (off/r) [A + r² e₁e₁ᵀ],   A = (I + rS)(I + rSᵀ),

    so by Sherman–Morrison T⁻¹B = (r/off) A⁻¹(B − γ e₁ (gᵀB)), g = A⁻¹e₁, γ = r²/(1 + r² g₁)
    (precomputed): the correction touches the first row of B only, before the solve. A⁻¹ is two
    bidiagonal solves, each the recurrence u_i = b_i − r u_{i∓1}, evaluated by recursive
    doubling: after the updates u_i ← u_i + (−r)^{2^j} u_{i∓2^j}, j = 0 … J−1, u_i holds every
    term (−r)^m b_{i∓m} with m < 2^J; J stops when 2^J ≥ n (exact) or when the terms left,
    ≤ |r|^{2^J}/(1 − |r|)·max|b|, are below `DOUBLING_TAIL`·max|b| (5 updates each for
    tri(1, 4, 1)). Every update writes a contiguous range in place, and the last one is the
    result. off = 0 is T = diag·I.
    """

    def __init__(self, diag: float, off: float, n: int):
        self.n, self.diag, self.off = n, float(diag), float(off)
        if off == 0.0:
            return
        ratio = diag / off
        if not abs(ratio) > 2.0:
            raise ValueError(f"tri(off, diag, off) needs |diag| > 2|off| (diagonal dominance), got diag = {diag}, off = {off}")
        self.r = float(np.sign(ratio) * (abs(ratio) / 2.0 - np.sqrt((ratio / 2.0) ** 2 - 1.0)))
        coefficient, shift, self.levels = -self.r, 1, []
        while shift < n:
            self.levels.append((shift, coefficient))
            shift, coefficient = 2 * shift, coefficient * coefficient
            if abs(coefficient) / (1.0 - abs(self.r)) <= DOUBLING_TAIL:
                break
        e1 = np.zeros(n)
        e1[0] = 1.0
        self.g = self._sweeps_numpy(e1)
        self.gamma = self.r**2 / (1.0 + self.r**2 * self.g[0])

    def _sweeps_numpy(self, b):
        """(I + rSᵀ)⁻¹(I + rS)⁻¹ b, sequentially (numpy; construction time only)."""
        u = np.array(b, dtype=float)
        for i in range(1, len(u)):
            u[i] -= self.r * u[i - 1]
        for i in range(len(u) - 2, -1, -1):
            u[i] -= self.r * u[i + 1]
        return u

    def _recurrence(self, u, k: int, forward: bool):
        """u_i ← solution of u_i + r u_{i−1} = b_i (forward) or u_i + r u_{i+1} = b_i, rows of k."""
        for shift, coefficient in self.levels:
            s = k * shift
            if forward:
                u = _put(u, u[s:] + coefficient * u[:-s], s)
            else:
                u = _put(u, u[:-s] + coefficient * u[s:], 0)
        return u

    def solve(self, B, k: int = 3, scale: float | jnp.ndarray = 1.0):
        """scale · T⁻¹ B."""
        if self.off == 0.0:
            return B * (scale / self.diag)
        U = B * (scale * self.r / self.off)
        U = _put(U, U[:k] - self.gamma * _rows_dot(self.g, U, k), 0)
        return self._recurrence(self._recurrence(U, k, True), k, False)

    def solve_numpy(self, b) -> np.ndarray:
        """T⁻¹ b for one column b (n,), sequentially (numpy; construction time only)."""
        if self.off == 0.0:
            return np.asarray(b, dtype=float) / self.diag
        V = self._sweeps_numpy(b)
        return (self.r / self.off) * (V - self.gamma * self.g * V[0])

    def dense_inverse(self) -> np.ndarray:
        T = self.diag * np.eye(self.n) + self.off * (np.eye(self.n, k=1) + np.eye(self.n, k=-1))
        return np.linalg.inv(T)


@functools.lru_cache(maxsize=64)
def _toeplitz(diag: float, off: float, n: int) -> ToeplitzTridiagonal:
    """The interior's factors depend on the mass model and N only (shared by every model)."""
    return ToeplitzTridiagonal(diag, off, n)


class ClosedFormEOM:
    """Hand-derived M(x, R), p = M w and ẇ of a `StringPendulum` (same layout, same physics).

    ``tri_solve``: how the interior block is inverted, "doubling" (`ToeplitzTridiagonal`,
    O(N)) or "dense" (a product with the precomputed T⁻¹, O(N²); a reference); "auto" is
    "doubling".
    """

    def __init__(self, model: StringPendulum, tri_solve: str = "auto"):
        if tri_solve not in TRI_SOLVERS:
            raise ValueError(f"tri_solve = {tri_solve!r} is invalid (allowed: {', '.join(map(repr, TRI_SOLVERS))})")
        self.model = model
        self.layout = model.layout
        m = model
        self.N, self.mu, self.m_b, self.L = m.N, m.mu, m.m_b, m.L  # κ_d enters only through M0 (the model's)
        N = self.N
        # numpy for a model built from a scene, jax.numpy for one whose numbers are run-time
        # values of a compiled program (`StringPendulum.bind`): then these are computed in it
        xp = jnp if m.is_bound else np
        self.c31, self.c23 = xp.asarray(m.c31), xp.asarray(m.c23)
        # per-row constants of the flat node vectors: c23_{b−1}, c31_b, c31_{b−1} for rows b = 2 … N+1
        self._c23_rows = xp.repeat(self.c23, 3)
        self._c31_next_rows = xp.repeat(xp.concatenate([self.c31[1:], xp.zeros(1)]), 3)
        self._c31_rows = xp.repeat(self.c31, 3)
        self.rho_c, self.J_o, self.J_c = xp.asarray(m.rho_c), xp.asarray(m.J_o), xp.asarray(m.J_c)
        r, z = self.rho_c, xp.zeros_like(self.rho_c[0])
        self.rho_hat = xp.stack([xp.stack([z, -r[2], r[1]]), xp.stack([r[2], z, -r[0]]), xp.stack([-r[1], r[0], z])])
        n = N - 1  # interior free nodes 2..N
        self.n_int = n
        self.tri_solve = "doubling" if tri_solve == "auto" else tri_solve
        # string mass = (μl/den)·tri(o, 2d, o), last diagonal d (models.model.StringMass);
        # consistent: tri(1, 4, 1) and 2 below, lumped: diagonal
        sm = m.string_mass
        self.mass_den, self.mass_d, self.mass_o = sm.den, sm.d, sm.o
        #: diagonal of the string mass over nodes 2 … N+1, in units of μl/den
        self._mass_diag_rows = _per_node(np.concatenate([2.0 * sm.d * np.ones(n), [sm.d]]))
        #: node N+1's diagonal after eliminating the interior, in units of μl/den: d − o z_last
        self._tip_diag = float(sm.d)
        if n > 0:
            self._interior = _toeplitz(2.0 * sm.d, sm.o, n)
            self._tri_inv = self._interior.dense_inverse() if self.tri_solve == "dense" else None
            #: z = o T⁻¹ e_last (constant): the coupling of the interior to node N+1
            self._z = sm.o * self._interior.solve_numpy(np.eye(n)[-1])
            self._tip_diag = float(sm.d - sm.o * self._z[-1])

    # ------------------------------------------------------------------------------------
    # Pieces
    # ------------------------------------------------------------------------------------
    def _coupling(self, D):
        """C_b = c31_b D_b + c23_{b−1} D_{b−1}, rows b = 2 … N+1, from D_a, rows a = 1 … N (flat)."""
        return self._c23_rows * D + self._c31_next_rows * _from_next(D)

    def _elements(self, qf):
        """D_a = q_a − q_{a+1}, rows a = 1 … N (flat), from q_2 … q_{N+1} (flat; q_1 = 0)."""
        return _from_prev(qf) - qf

    def _string_apply(self, vf, l):
        """S(v)_b = (μl/den)(o v_{b−1} + diag_b v_b + o v_{b+1}), rows b = 2 … N+1 (flat; v_1 = 0)."""
        o = self.mass_o
        inner = self._mass_diag_rows * vf
        if o:
            inner = inner + o * (_from_prev(vf) + _from_next(vf))
        return (self.mu * l / self.mass_den) * inner

    def _body_frame(self, R):
        """W = R ρ_c^ (M_{N+1,Ω} = −m_b W)."""
        return _matmul(R, jnp.asarray(self.rho_hat))

    def J_body(self, R):
        """M_ΩΩ = J_c − m_b ρ_c^ (RᵀR) ρ_c^ = J_c + m_b WᵀW (= J_o when R is orthogonal; the
        ODE state's R(quat) is not renormalised, so this keeps the model's T_body exactly)."""
        return jnp.asarray(self.J_c) + self.m_b * _gram(self._body_frame(R))

    def M0(self, s):
        return self.model.reel_mass(s)  # the one definition (StringPendulum.reel_mass)

    def _join(self, s, nodes, omega):
        """A vector over w's layout from its parts (s scalar or None, nodes flat (3N,), Ω or None)."""
        lay = self.layout
        placed = [(lay.nodes.start, nodes)]
        if lay.has_reel:
            placed.append((0, jnp.reshape(s, (1,))))
        if lay.has_attitude:
            placed.append((lay.omega.start, omega))
        return _assemble(lay.nw, *placed)

    def _join_solution(self, a_s, A, a_L, alpha, offset: int = 0, buf=None):
        """The solution (a_s, interior accelerations A flat (3n,) or None, a_L, α) written over
        w's layout, at `offset` into buf (a new zero vector over w when buf is None)."""
        lay = self.layout
        if buf is None:
            buf = jnp.zeros(lay.nw)
        start = offset + lay.nodes.start
        if A is not None:
            buf = _put(buf, A, start)
        buf = _put(buf, a_L, start + 3 * self.n_int)
        if lay.has_reel:
            buf = _put(buf, jnp.reshape(a_s, (1,)), offset)
        if lay.has_attitude:
            buf = _put(buf, alpha, offset + lay.omega.start)
        return buf

    def _parts(self, vec):
        """(s part or None, node part flat (3N,), Ω part or None) of a vector over w's layout."""
        lay = self.layout
        return (vec[0] if lay.has_reel else None, vec[lay.nodes],
                vec[lay.omega] if lay.has_attitude else None)

    # ------------------------------------------------------------------------------------
    # Legendre transform
    # ------------------------------------------------------------------------------------
    def momentum(self, x, R, w):
        """p = M(x, R) w, structured (O(N)):
        p_s = M0 ṡ + Σ_b C_b·v_b,  p_b = S(v)_b + ṡ C_b (+ m_b (v_{N+1} + R c) on node N+1),
        p_Ω = M_ΩΩ Ω + m_b ρ_c × u."""
        lay, N = self.layout, self.N
        qf, vf, l = x[lay.nodes], w[lay.nodes], self.model.element_length(x)
        pq = self._string_apply(vf, l)
        v_tip = vf[3 * N - 3:]
        tip = self.m_b * v_tip
        p_s = p_om = None
        if lay.has_attitude:
            om, rho = w[lay.omega], jnp.asarray(self.rho_c)
            Rc = _matvec(R, _cross(om, rho))
            tip = tip + self.m_b * Rc
            p_om = (_matvec(jnp.asarray(self.J_c), om) + self.m_b * _cross(rho, _rmatvec(R, Rc))
                    + self.m_b * _cross(rho, _rmatvec(R, v_tip)))
        if lay.has_reel:
            sd = w[0]
            C = self._coupling(self._elements(qf))
            p_s = self.M0(x[0]) * sd + jnp.sum(C * vf)
            pq = pq + sd * C
        pq = _put(pq, pq[3 * N - 3:] + tip, 3 * N - 3)
        return self._join(p_s, pq, p_om)

    def mass_matrix(self, x, R):
        """M(x, R) assembled block-wise (dense nw × nw; a reference for the structured solve)."""
        lay, N = self.layout, self.N
        l = self.model.element_length(x)
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
            C = self._coupling(self._elements(x[lay.nodes]))
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
        """(F_s or None, F_q flat (3N,), F_Ω or None) of F = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w."""
        m, lay, N = self.model, self.layout, self.N
        dV_s, dV_q, dV_om = self._parts(m.potential_gradient(x, R))
        Fq = -dV_q
        Fs = F_om = None
        Q_om = None
        if m.string_forces or m.body_loads:
            Q_s, Q_q, Q_om = self._parts(m.loads(t, x, R, w))
            Fq = Fq + Q_q
        if lay.has_reel:
            mu, sd = self.mu, w[0]
            vf, l = w[lay.nodes], m.element_length(x)
            va = _from_prev(vf)  # v_{b−1}, rows b = 2 … N+1 (= v_a of element a = b − 1)
            quad = jnp.sum(va * va + va * vf + vf * vf)
            Cdot = self._coupling(va - vf)
            Fs = (mu / 3.0 - 2.0 * mu / 3.0) * sd * sd - mu / (6.0 * N) * quad - jnp.sum(Cdot * vf)
            Fs = Fs - dV_s + m.reel_force(t, x, w)
            if m.string_forces or m.body_loads:
                Fs = Fs + Q_s
            G = self._c31_rows * va + self._c23_rows * vf  # G_a, rows a = 1 … N
            Fq = Fq + sd * (_from_next(G) - G - Cdot) + (sd / (N * l)) * self._string_apply(vf, l)
        if lay.has_attitude:
            mb, om, rho = self.m_b, w[lay.omega], jnp.asarray(self.rho_c)
            c = _cross(om, rho)
            Pc = _rmatvec(R, _matvec(R, c))
            u = _rmatvec(R, w[lay.nodes][3 * N - 3:])
            R_om_c = _matvec(R, _cross(om, c))
            Fq = _put(Fq, Fq[3 * N - 3:] - mb * R_om_c, 3 * N - 3)
            Pi = _matvec(jnp.asarray(self.J_c), om) + mb * _cross(rho, Pc) + mb * _cross(rho, u)
            Pdot_c = _rmatvec(R, R_om_c) - _cross(om, Pc)
            F_om = (_cross(Pi, om) + mb * _cross(c, u) + mb * _cross(rho, _cross(om, u)) - dV_om
                    # terms that vanish for orthogonal R (P = RᵀR = I): M_R and Ṁ w of ½ m_b cᵀ P c
                    + mb * (_cross(c, Pc) - _cross(rho, Pdot_c)))
            if m.body_loads:  # the moment on the body (body frame)
                F_om = F_om + Q_om
        return Fs, Fq, F_om

    def force(self, t, x, R, w):
        """F = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w (so that M ẇ = F), over w's layout."""
        return self._join(*self._force_parts(t, x, R, w))

    # ------------------------------------------------------------------------------------
    # Structured solve of M a = F
    # ------------------------------------------------------------------------------------
    def _tri_inv_apply(self, B, scale):
        """scale · T⁻¹ B for B flat (3n,), T = tri(o, 2d, o)."""
        if self.tri_solve == "dense":
            return scale * (jnp.asarray(self._tri_inv) @ B.reshape(self.n_int, 3)).reshape(-1)
        return self._interior.solve(B, 3, scale)

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
        """(a_s, A flat (3n,) or None, a_L, α) of M a = F.

        The interior rows h T A + o h e_last a_Lᵀ + C_int a_s = r_int (h = μl/den) give
        A = T⁻¹(r_int − C_int a_s − o h e_last a_Lᵀ)/h. Substituted into the rows of s and of
        node N+1 they leave the border system of `_border_solve`, whose coefficients need only
        z = o T⁻¹ e_last (a constant) and, with a reel, ZC = T⁻¹ C_int / h (T⁻¹ is symmetric):

            dL = h (d − o z_last) + m_b,  f_L = r_L − Σ_i z_i r_i,  c_L = C_L − Σ_i z_i C_i,
            σ0 = M0 − Σ_i C_i·ZC_i,  f_s = F_s − Σ_i ZC_i·r_i   (sums over interior nodes).

        So the interior is solved once, after the border, for its final right-hand side (and
        once before it for ZC with a reel)."""
        lay, n, N = self.layout, self.n_int, self.N
        h = self.mu * self.model.element_length(x) / self.mass_den
        o = self.mass_o
        has_s = lay.has_reel
        C = self._coupling(self._elements(x[lay.nodes])) if has_s else None
        tip = 3 * N - 3
        r_int, r_L = Fq[:tip], Fq[tip:]
        dL = h * self._tip_diag + self.m_b
        s_block = None
        if n > 0:
            f_L = r_L - _rows_dot(self._z, r_int)
            if has_s:
                C_int = C[:tip]
                ZC = self._tri_inv_apply(C_int, 1.0 / h)
                s_block = (self.M0(x[0]) - jnp.sum(C_int * ZC), C[tip:] - _rows_dot(self._z, C_int),
                           Fs - jnp.sum(ZC * r_int))
        else:
            f_L = r_L
            if has_s:
                s_block = (self.M0(x[0]), C[tip:], Fs)
        a_s, a_L, alpha = self._border_solve(R, dL, f_L, s_block, F_om)
        A = None
        if n > 0:
            b = r_int - C_int * a_s if has_s else r_int
            if o:
                b = _put(b, b[tip - 3:] - (o * h) * a_L, tip - 3)
            A = self._tri_inv_apply(b, 1.0 / h)
        return a_s, A, a_L, alpha

    def solve(self, x, R, F):
        """a = M(x, R)⁻¹ F by a Schur complement on (s̈, q̈_{N+1}, Ω̇), O(N)."""
        return self._join_solution(*self._solve_parts(x, R, *self._parts(F)))

    def accelerations(self, t, x, R, w):
        """ẇ from M ẇ = [∂L/∂x + Q ; Π × Ω + M_R] − Ṁ w, closed form, O(N) structured solve."""
        return self._join_solution(*self._solve_parts(x, R, *self._force_parts(t, x, R, w)))

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
        """ẏ = (ẋ = w_x, q̇uat = ½ quat ⊗ (0, Ω), ẇ, Ẇ = Q·w), written into one buffer."""
        m, lay = self.model, self.layout
        x, R, w, _ = m.split_state(y)
        placed = [(lay.y_x.start, w[: lay.nx])]
        if lay.has_attitude:
            placed.append((lay.y_quat.start, quat_rate(y[lay.y_quat], w[lay.omega])))
        if lay.has_work:
            placed.append((lay.y_work.start, jnp.reshape(m.power(t, x, w, R), (1,))))
        buf = _assemble(lay.ny, *placed)
        return self._join_solution(*self._solve_parts(x, R, *self._force_parts(t, x, R, w)), lay.y_w.start, buf)

    @functools.cached_property
    def ode_rhs_jit(self):
        return jax.jit(self.ode_rhs)


@functools.lru_cache(maxsize=64)
def build_closed_form(scene) -> ClosedFormEOM:
    """The closed-form equations of a scene (cached like `models.build_model`)."""
    from reelbench.models.model import build_model

    return ClosedFormEOM(build_model(scene))
