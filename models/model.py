"""The string pendulum model: the single source of truth for the physics (described in models/README.md).

`StringPendulum(scene)` composes the energy terms and generalized forces of the scene's
effects (each defined in `models.effects`), once, at construction. The kinetic energy of the
string and of the end mass is structural and lives here (the one derivation the autodiff
path, `models.closed_form` and the LGVI read); the effects add T_reel and the rigid body's
T_body. Everything else is derived from those terms:

* the continuous equations of motion by automatic differentiation of the
  Lagrangian (`accelerations`, `ode_rhs` on a quaternion attitude state), checked in the tests
  against the closed-form equations of `models.closed_form`;
* the Legendre transform p = M(x, R) w and its inverse, used by every integrator;
* the diagnostics (`models.diagnostics`).

All functions take unbatched JAX arrays: x (nx,), R (3, 3), w (nw,) — see `models.layout`.
Without a rigid body R is ignored (pass the identity).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np

from reelbench.models._jax import jax, jnp
from reelbench.models.effects import get_effect
from reelbench.models.layout import StateLayout
from reelbench.models.scene import Scene


def hat(v):
    """Hat map: hat(v) @ y = v × y."""
    return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _two_sided(stretch, l):
    """Elastic length of the paper's law: the stretch itself (resists compression too).
    `slack` replaces it (`models.effects.Slack.elastic_law`)."""
    return stretch


def _two_sided_tension(tension):
    return tension


def vee(m):
    """Inverse of `hat` (skew part of m)."""
    return jnp.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) * 0.5


def quat_to_rot(quat):
    """R(quat) for quat = (w, x, y, z) by the usual formula, *not* renormalised."""
    w, x, y, z = quat
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_to_rot_many(quats) -> np.ndarray:
    """`quat_to_rot` of each row of ``quats`` (n, 4), in numpy: the same formula in the same order
    (equal bit for bit, tested), for the host's per-run metrics, where one eager JAX call per
    saved quaternion took 0.25 ms each (0.1-0.2 s a run)."""
    q = np.asarray(quats, dtype=float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rot_to_quat(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (numpy; Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q, dtype=float)
    return q if q[0] >= 0 else -q


def _number(value) -> float:
    return 0.0 if value is None else float(value)


def _builtin_effects() -> frozenset:
    from reelbench.models.effects import _BUILTIN

    return _BUILTIN


#: The model's numbers: every attribute a scene supplies as a value (and the ones derived from
#: them on the host), what `StringPendulum.values` returns and `StringPendulum.bind` substitutes.
#: What is not here is structure (N, the effects, the mass model, the layout, branches on values
#: such as `drag_at_offset`): the key of a compiled program (`StringPendulum.structure_key`).
VALUE_NAMES = ("L", "mu", "EA", "m_b", "J_c", "rho_c", "J_o", "J_d", "d", "r_d", "b", "kappa", "r_p", "t_g", "u",
               "ell_min", "g", "s_fixed", "c31", "c23", "axial_damping", "fluid_density", "string_diameter",
               "body_volume", "normal_drag", "tangential_drag", "drag_area", "current")


@dataclass(frozen=True)
class StringMass:
    """The string's element mass matrix (μ l / den)·[[d, o], [o, d]] (`string.mass_model`).

    The one place the string mass comes from: the autodiff kinetic energy, the closed form
    (`models.closed_form`) and the LGVI (`integrators._lgvi_core`) all read these numbers.
    Assembled over nodes 2 … N+1 it is (μ l / den)·tridiag(o, 2d, o), last diagonal entry d
    (before the body mass). Written as small integers over a denominator so that the
    consistent matrix is evaluated exactly as before this option existed (μ l / 6 times 1, 4, 1).
    """

    den: float
    d: float  # diagonal entry of the element matrix
    o: float  # off-diagonal entry (node a with node a+1)


#: "consistent": linear elements, (μl/6)[[2, 1], [1, 2]]; "lumped": half of each element's
#: mass at each end node, (μl/2)[[1, 0], [0, 1]] (MoorDyn's and a MuJoCo chain's masses).
STRING_MASS = {"consistent": StringMass(6.0, 2.0, 1.0), "lumped": StringMass(2.0, 1.0, 0.0)}


def quat_rate(quat, omega):
    """q̇uat = ½ quat ⊗ (0, Ω), Ω in the body frame."""
    w, x, y, z = quat
    p, q, r = omega
    return 0.5 * jnp.array(
        [-x * p - y * q - z * r, w * p + y * r - z * q, w * q + z * p - x * r, w * r + x * q - y * p]
    )


class StringPendulum:
    """Energy, forces and continuous-time equations of one scene (models/README.md).

    Only the effects the scene lists exist: without `reel`, s_p is not a coordinate; without
    `rigid_body`, the end mass is a point mass and there is no attitude state.
    """

    def __init__(self, scene: Scene):
        self.scene = scene
        self.layout = StateLayout.from_scene(scene)
        st, bd, rl, ini = scene.string, scene.body, scene.reel, scene.initial
        self.N = st.elements
        self.L = st.total_length
        self.mu = st.mass_per_length
        self.EA = st.axial_stiffness
        self.m_b = bd.mass
        self.J_c = np.array(bd.inertia)
        self.rho_c = np.array(bd.attachment_to_com) if scene.has("rigid_body") else np.zeros(3)
        rho = self.rho_c
        #: inertia about the attachment point, and the LGVI's nonstandard inertia J_d
        self.J_o = self.J_c + self.m_b * (rho @ rho * np.eye(3) - np.outer(rho, rho))
        self.J_d = 0.5 * np.trace(self.J_o) * np.eye(3) - self.J_o
        self.d = rl.radius
        self.r_d = np.array(rl.center)
        self.b = rl.guide_length
        self.kappa = rl.equivalent_mass
        self.r_p = np.array(rl.exit_point)
        self.t_g = np.array(rl.exit_direction)
        self.u = rl.control_moment if scene.has("reel_control") else 0.0
        self.ell_min = rl.min_deployed_length
        self.g = scene.g if scene.has("gravity") else 0.0
        #: s_p of a fixed-length scene (locked)
        self.s_fixed = self.L - ini.deployed_length
        a = np.arange(1, self.N + 1, dtype=float)
        # axial-flow coupling of the deployed string: M31_a = c31_a (q_a - q_{a+1}), M23_a = c23_a (q_a - q_{a+1})
        self.c31 = self.mu / (6 * self.N) * (2 + 3 * self.N - 3 * a)
        self.c23 = self.mu / (6 * self.N) * (1 + 3 * self.N - 3 * a)
        #: element mass matrix of `string.mass_model` (the scene refuses "lumped" with a reel:
        #: M0 and the M31/M23 coupling above are the consistent element's axial-flow terms)
        self.string_mass = STRING_MASS[scene.string.mass_model]

        # Effects -> terms, decided once here (not by branches in the integrators): every listed
        # effect contributes its own terms (models/effects.py); the structural kinetic terms of
        # the string and of a point-mass body are the model's, the reel adds T_reel and
        # `rigid_body` replaces T_body.
        # The required effects (the string's own elasticity) are composed first, the others in
        # canonical order: the totals then add up in the order of the closed form this replaced,
        # so fixed-length results are bit-identical to it.
        listed = [get_effect(e) for e in scene.effects]
        self.effects = tuple([e for e in listed if e.required] + [e for e in listed if not e.required])
        # the effects' own numbers (0 where the effect is not listed: read only by its terms)
        st_d, fl, bdy = scene.section("string"), scene.section("fluid"), scene.section("body")
        self.axial_damping = _number(st_d.get("axial_damping"))
        self.fluid_density = _number(fl.get("density"))
        self.string_diameter = _number(st_d.get("diameter"))
        self.body_volume = _number(bdy.get("volume"))
        self.normal_drag = _number(st_d.get("normal_drag"))
        self.tangential_drag = _number(st_d.get("tangential_drag"))
        self.drag_area = _number(bdy.get("drag_area"))
        self.current = np.asarray(fl.get("current") or (0.0, 0.0, 0.0), dtype=float)
        #: the body's drag acts at an offset centre of mass (a body load: `models.effects.Drag`):
        #: a branch of the terms, so part of the structure, decided here from the scene's values
        self.drag_at_offset = bool(scene.has("drag") and self.layout.has_attitude and np.any(self.rho_c != 0.0)
                                   and self.drag_area > 0)
        #: built-in effects read every number from the model when called (`bind` substitutes
        #: them); a plugin's terms may hold numbers of their own, so its model shares no program
        self.shares_programs = all(e.name in _builtin_effects() for e in self.effects)
        self._composed = self.effects
        #: True for a copy made by `bind` (its numbers may be traced: cache nothing derived from it)
        self.is_bound = False
        self._compose()

    def _compose(self):
        """The terms of the listed effects, built on this model's attributes (again by `bind`)."""
        # Elastic law: the length that stores strain energy. Two-sided (the paper's: resists
        # compression too) unless an effect (`slack`) replaces it; set before the terms that read it.
        self._taut_length, self._clip_tension = _two_sided, _two_sided_tension
        for effect in self._composed:
            law = effect.elastic_law(self)
            if law is not None:
                self._taut_length, self._clip_tension = law
        self.kinetic_terms: dict[str, Callable] = {"T_string": self._T_string, "T_body": self._T_point_mass}
        self.potential_terms: dict[str, Callable] = {}
        self.potential_gradients: dict[str, Callable] = {}
        #: which effect contributed each term (diagnostics group the potential terms by it)
        self.term_owner: dict[str, str] = {}
        # Non-conservative generalized forces, three kinds, composed by `generalized_force`:
        # reel forces act on s_p only and depend on w only through ṡ_p (scalar terms);
        # string forces are vectors over w's layout acting on (s_p, q) (not on Ω);
        # body loads may also act on Ω and depend on R.
        self.reel_forces: dict[str, Callable] = {}
        self.string_forces: dict[str, Callable] = {}
        #: loads on the body (`Effect.body_loads`): vectors over w's layout of (t, x, R, w) that
        #: may act on Ω (a moment in the body frame) and depend on the attitude
        self.body_loads: dict[str, Callable] = {}
        for effect in self._composed:
            self.kinetic_terms.update(effect.kinetic(self))
            for name, term in effect.potentials(self).items():
                self.potential_terms[name] = term.energy
                self.potential_gradients[name] = term.gradient
                self.term_owner[name] = effect.name
            for kind, hook in ((self.reel_forces, effect.reel_forces), (self.string_forces, effect.string_forces),
                               (self.body_loads, effect.body_loads)):
                for name, f in hook(self).items():
                    kind[name] = f
                    self.term_owner[name] = effect.name

    # ------------------------------------------------------------------------------------
    # Values and structure: what a compiled program takes as arguments and what it is keyed by
    # ------------------------------------------------------------------------------------
    @functools.cached_property
    def program_effects(self) -> tuple:
        """The effects a compiled program of this model composes: the listed ones, plus those
        that vanish when unlisted (`Effect.zero_when_unlisted`, e.g. `reel_control` with u = 0)
        where they need no new coordinate, in the order `__init__` composes them."""
        from reelbench.models.effects import EFFECTS

        listed = {e.name for e in self.effects}
        extra = {e.name for e in EFFECTS.values()
                 if e.zero_when_unlisted and e.name not in listed and e.name in _builtin_effects() and all(n in listed for n in e.needs)
                 and not e.state and (self.layout.has_work or not e.forcing)}
        if not extra or not self.shares_programs:
            return self.effects
        every = [e for e in EFFECTS.values() if e.name in listed | extra]
        return tuple([e for e in every if e.required] + [e for e in every if not e.required])

    def structure_key(self):
        """Hashable: what a compiled program of this model depends on besides `values` (two
        models with equal keys run the same program with their own values). A model with an
        effect that is not built in is keyed by its scene (its terms may hold numbers)."""
        if not self.shares_programs:
            return ("model", self)
        return ("structure", self.N, tuple(e.name for e in self.program_effects), self.scene.string.mass_model,
                self.drag_at_offset)

    @functools.cached_property
    def _values(self) -> dict:
        return {k: np.asarray(getattr(self, k), dtype=np.float64) for k in VALUE_NAMES}

    def values(self) -> dict:
        """{name: float64 array} of the model's numbers (`VALUE_NAMES`): the run-time argument
        of its compiled programs, to `bind` inside them."""
        return dict(self._values)

    def value_vector(self) -> np.ndarray:
        """`values` packed in one float64 vector (`VALUE_NAMES` order, each raveled): one argument
        instead of dozens (a call from numpy pays for each argument: scipy's right-hand side)."""
        return np.concatenate([np.ravel(v) for v in self._values.values()])

    def bind(self, values) -> "StringPendulum":
        """A copy of this model whose numbers are ``values`` (`values`, or packed as
        `value_vector`; traced, inside a compiled program) and whose terms are composed again on
        them, from `program_effects`. Its scene is this model's (read for structure only). A
        model that shares no programs returns itself."""
        if not self.shares_programs:
            return self
        import copy

        new = copy.copy(self)
        for k in ("ode_rhs_jit", "ode_jacobian_jit", "_values"):
            new.__dict__.pop(k, None)
        if isinstance(values, dict):
            for k in VALUE_NAMES:
                setattr(new, k, values[k])
        else:
            # packed: each number is sliced from the vector where it is read (`__getattr__`), so
            # that a loop or branch inside the program takes the one vector as its operand, not
            # dozens of numbers (measured: XLA CPU's loops then run as fast as with constants)
            slots, start = {}, 0
            for k, v in self._values.items():
                slots[k] = (start, v.size, v.shape)
                start += v.size
                del new.__dict__[k]
            new.__dict__["_value_slots"], new.__dict__["_value_vector"] = slots, values
        new._composed = self.program_effects
        new.is_bound = True
        new._compose()
        return new

    def __getattr__(self, name):
        # only for names not in the instance: a bound model's numbers, read from its vector
        slots = self.__dict__.get("_value_slots")
        if slots is not None and name in slots:
            start, size, shape = slots[name]
            return self.__dict__["_value_vector"][start:start + size].reshape(shape)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def terms_of(self, effect: str) -> tuple[str, ...]:
        """Names of the potential terms and forces an effect contributed (empty if not listed)."""
        return tuple(k for k, e in self.term_owner.items() if e == effect)

    # ------------------------------------------------------------------------------------
    # Coordinates
    # ------------------------------------------------------------------------------------
    def reel_coordinate(self, x):
        return x[0] if self.layout.has_reel else jnp.asarray(self.s_fixed)

    def nodes(self, x):
        """Node positions relative to r_p, (N+1, 3), with q_1 = 0."""
        q = x[self.layout.nodes].reshape(self.N, 3)
        return jnp.concatenate([jnp.zeros((1, 3)), q], axis=0)

    def element_length(self, x):
        """Unstretched element length l = (L - s_p) / N."""
        return (self.L - self.reel_coordinate(x)) / self.N

    def reel_rate(self, w):
        return w[0] if self.layout.has_reel else jnp.asarray(0.0)

    def node_velocities(self, w):
        qd = w[self.layout.nodes].reshape(self.N, 3)
        return jnp.concatenate([jnp.zeros((1, 3)), qd], axis=0)

    def omega(self, w):
        return w[self.layout.omega] if self.layout.has_attitude else jnp.zeros(3)

    # ------------------------------------------------------------------------------------
    # Energy terms, one per effect
    # ------------------------------------------------------------------------------------
    def reel_mass(self, s):
        """M0(s) = μ s + κ_d + μ (L − s)/3: the s_p diagonal of the mass matrix (the stored
        string, the reel's equivalent mass and the deployed string's axial flow). The one
        definition: the autodiff T (`_T_reel`), the closed form (`ClosedFormEOM.M0`) and the
        LGVI's discrete equations (`integrators._lgvi_core`) all call it."""
        return self.mu * s + self.kappa + self.mu * (self.L - s) / 3.0

    def _T_reel(self, x, R, w):
        s, sd = x[0], w[0]
        return 0.5 * self.reel_mass(s) * sd * sd

    def _T_string(self, x, R, w):
        q, qd, l = self.nodes(x), self.node_velocities(w), self.element_length(x)
        va, vb = qd[:-1], qd[1:]
        sm = self.string_mass
        hd = 0.5 * sm.d  # ½ vᵀ M v per element = (μl/den)(hd|va|² + o va·vb + hd|vb|²)
        T = jnp.sum(self.mu * l / sm.den * (hd * jnp.sum(va * va, 1) + sm.o * jnp.sum(va * vb, 1) + hd * jnp.sum(vb * vb, 1)))
        if self.layout.has_reel:
            dq = q[:-1] - q[1:]
            coupling = jnp.sum(self.c31 * jnp.sum(dq * va, 1) + self.c23 * jnp.sum(dq * vb, 1))
            T = T + w[0] * coupling
        return T

    def _T_point_mass(self, x, R, w):
        """T_body without `rigid_body`: a point mass m_b at node N+1."""
        v_tip = self.node_velocities(w)[-1]
        return 0.5 * self.m_b * v_tip @ v_tip

    def _T_rigid_body(self, x, R, w):
        """T_body with `rigid_body`: ½ m_b |v_{N+1} + R(Ω × ρ_c)|² + ½ Ω·J_c Ω (the LGVI's
        discrete form is pinned to it in tests/test_lgvi.py)."""
        v_tip = self.node_velocities(w)[-1]
        om = self.omega(w)
        v_com = v_tip + R @ jnp.cross(om, self.rho_c)
        return 0.5 * self.m_b * v_com @ v_com + 0.5 * om @ (self.J_c @ om)

    def over_w(self, ds=None, dq=None, deta=None):
        """A vector over w's layout from its parts (zeros for parts not given; parts for
        coordinates the scene lacks are dropped). dq is (N, 3), nodes 2..N+1."""
        # written in place (dynamic_update_slice) rather than concatenated: XLA's CPU fusion
        # compiles a fused concatenate into a branch per element
        lay = self.layout
        out = jnp.zeros(lay.nw)
        if dq is not None:
            out = jax.lax.dynamic_update_slice(out, jnp.reshape(dq, -1), (lay.nodes.start,))
        if lay.has_reel and ds is not None:
            out = jax.lax.dynamic_update_slice(out, jnp.reshape(jnp.asarray(ds, dtype=float), (1,)), (0,))
        if lay.has_attitude and deta is not None:
            out = jax.lax.dynamic_update_slice(out, deta, (lay.omega.start,))
        return out

    def elements(self, x):
        """(Δ_a = q_{a+1} − q_a (N, 3), stretched lengths |Δ_a| (N,), unstretched length l) of the
        elements a = 1..N: what the elastic law, the damping and the tensions are written in."""
        qn = x[self.layout.nodes].reshape(self.N, 3)
        delta = jax.lax.dynamic_update_slice(qn, qn[1:] - qn[:-1], (1, 0))  # row 0: q_2 − q_1 = q_2
        return delta, jnp.sqrt(jnp.sum(delta * delta, axis=1)), self.element_length(x)

    def strain_rates(self, x, w):
        """ε̇_a = d/dt (|q_{a+1} − q_a| / l − 1) = ê_a·(q̇_{a+1} − q̇_a)/l + |q_{a+1} − q_a| ṡ_p/(N l²).

        (l = (L − s_p)/N, so l̇ = −ṡ_p/N; the ṡ_p term is absent for a fixed length.)
        """
        v = self.node_velocities(w)
        delta, stretch, l = self.elements(x)
        rate = jnp.sum(delta * (v[1:] - v[:-1]), axis=1) / (stretch * l)
        if self.layout.has_reel:
            rate = rate + stretch * self.reel_rate(w) / (self.N * l * l)
        return rate

    # ------------------------------------------------------------------------------------
    # Totals
    # ------------------------------------------------------------------------------------
    def kinetic(self, x, R, w):
        return sum(f(x, R, w) for f in self.kinetic_terms.values())

    def potential(self, x, R):
        return sum((f(x, R) for f in self.potential_terms.values()), jnp.asarray(0.0))

    def lagrangian(self, x, R, w):
        return self.kinetic(x, R, w) - self.potential(x, R)

    def energy(self, x, R, w):
        return self.kinetic(x, R, w) + self.potential(x, R)

    def reel_force(self, t, x, w):
        """The reel forces (Q_u + Q_c, on s_p only); zero without such effects.

        Not the whole s_p row of Q when string forces are present: see `generalized_force`.
        """
        return sum((f(t, x, w) for f in self.reel_forces.values()), jnp.asarray(0.0))

    def string_force(self, t, x, w):
        """Sum of the string forces (axial damping) as a vector over w; zeros without them."""
        return sum((f(t, x, w) for f in self.string_forces.values()), jnp.zeros(self.layout.nw))

    def body_load(self, t, x, R, w):
        """Sum of the body loads (`Effect.body_loads`) over w's layout; zeros without them. The
        Ω slot is the moment on the body about the attachment point, body frame."""
        return sum((f(t, x, R, w) for f in self.body_loads.values()), jnp.zeros(self.layout.nw))

    def loads(self, t, x, R, w):
        """The string forces plus the body loads: every non-conservative force but the reel
        forces (what the LGVI applies explicitly). Equal to `string_force` without body loads."""
        if not self.body_loads:
            return self.string_force(t, x, w)
        return self.string_force(t, x, w) + self.body_load(t, x, R, w)

    def generalized_force(self, t, x, w, R=None):
        """Q over w's layout: the reel forces in the s_p row plus the string forces plus the body
        loads (which need the attitude ``R``; a scene without them ignores it).

        (`accelerations` and `models.closed_form` add the same parts to their force side
        one by one: adding the reel force in place keeps scenes without string forces
        bit-identical to what they were before string forces existed.)
        """
        Q = jnp.zeros(self.layout.nw)
        if self.layout.has_reel and self.reel_forces:
            Q = Q.at[0].set(self.reel_force(t, x, w))
        if self.string_forces:
            Q = Q + self.string_force(t, x, w)
        if self.body_loads:
            if R is None:
                raise ValueError("generalized_force: this scene's body loads need the attitude R")
            Q = Q + self.body_load(t, x, R, w)
        return Q

    def power(self, t, x, w, R=None):
        """Power of the non-conservative forces, Q · w (accumulated as W): a body load's moment
        contributes Ω·M. ``R`` is needed only with body loads."""
        return self.generalized_force(t, x, w, R) @ w

    def potential_gradient(self, x, R):
        """Closed-form gradient of V over w's layout: (∂V/∂s_p, ∂V/∂q_2..q_{N+1}, ∂V/∂η).

        The sum of each potential term's own closed-form gradient (`models.effects`); ∂V/∂η
        is the derivative along R (I + η^). These are the D_s V and D_q V of the discrete equations; the tests
        check every term against autodiff of its energy.
        """
        return sum((g(x, R) for g in self.potential_gradients.values()), jnp.zeros(self.layout.nw))

    def tensions(self, x):
        """Elastic element tensions EA (|q_{a+1} - q_a| / l - 1), a = 1..N (negative = compression;
        clipped at 0 with `slack`). The damping tension c ε̇_a is not included (it needs w)."""
        _, stretch, l = self.elements(x)
        return self._clip_tension(self.EA * (stretch / l - 1.0))

    def deployed_length_margin(self, x):
        """Distance of the deployed length L - s_p from the ends of its range (ℓ_min, L - b).

        ℓ_min is ``reel.min_deployed_length`` (default 0). Positive inside the range; every
        integrator stops with status ``length_limit`` when it would become <= 0 (always
        positive for a fixed-length scene).
        """
        ell = self.L - self.reel_coordinate(x)
        return jnp.minimum(ell - self.ell_min, self.L - self.b - ell)

    def energy_scale(self) -> float:
        """The scene's energy scale in J (a fixed number, computed from the scene and its start):

            T(0) + Σ_terms |V_term(0)|  +  Σ_effects (what the effect can supply over the run)

        i.e. the initial kinetic energy, every initial potential term in absolute value (so that
        terms of opposite sign do not cancel), and each effect's `energy_scale`: for gravity the
        most potential energy it could release over the whole string length,
        g (m_b + μ L)(L + |ρ_c| + |r_d| + d); for the reel control the most work the constant
        moment can do over it, |u| L / d. Dissipative forces only remove what these supply. It
        is floored at 1e-9 J (a scene at rest with nothing to move it). Every integrator's
        energy guard is a multiple of it (`integrators.base.energy_bound`).
        """
        x0, R0, w0 = (jnp.asarray(a) for a in self.initial_state())
        T0 = float(self.kinetic(x0, R0, w0))
        V0 = sum(abs(float(f(x0, R0))) for f in self.potential_terms.values())
        total = T0 + V0
        for effect in self.effects:
            total += float(effect.energy_scale(self))
        return max(total, 1e-9)

    def length_limit_name(self, ell: float) -> str:
        """Which end of (ℓ_min, L - b) a deployed length ``ell`` is at (for status reasons)."""
        if abs(ell - self.ell_min) <= abs(self.L - self.b - ell):
            return f"its lower limit min_deployed_length = {self.ell_min:g} m"
        return f"its upper limit total_length - guide_length = {self.L - self.b:g} m (the string ran out)"

    # ------------------------------------------------------------------------------------
    # Legendre transform
    # ------------------------------------------------------------------------------------
    def momentum(self, x, R, w):
        """p = ∂L/∂w = M(x, R) w (T is exactly quadratic in w)."""
        return jax.grad(self.kinetic, argnums=2)(x, R, w)

    def mass_matrix(self, x, R):
        return jax.jacfwd(self.momentum, argnums=2)(x, R, jnp.zeros(self.layout.nw))

    def velocity_from_momentum(self, x, R, p):
        return jnp.linalg.solve(self.mass_matrix(x, R), p)

    # ------------------------------------------------------------------------------------
    # Continuous-time equations, by autodiff of the Lagrangian
    # ------------------------------------------------------------------------------------
    def accelerations(self, t, x, R, w):
        """ẇ from M ẇ = [∂L/∂x + Q ; Π × Ω + M_R] - Ṁ w."""
        lay = self.layout
        M = self.mass_matrix(x, R)
        xdot = w[: lay.nx]
        om = self.omega(w)
        Rdot = R @ hat(om)
        # Ṁ w: derivative of M(x, R) w along (ẋ, R Ω^) with w held fixed
        _, Mdot_w = jax.jvp(lambda x_, R_: self.momentum(x_, R_, w), (x, R), (xdot, Rdot))
        rhs = jax.grad(self.lagrangian, argnums=0)(x, R, w)
        if lay.has_reel:
            rhs = rhs.at[0].add(self.reel_force(t, x, w))
        if lay.has_attitude:
            # M_R · η = d/dε L(R exp(ε η^)); first order needs only R (I + ε η^)
            M_R = jax.grad(lambda eta: self.lagrangian(x, R @ (jnp.eye(3) + hat(eta)), w))(jnp.zeros(3))
            Pi = self.momentum(x, R, w)[lay.omega]
            rhs = jnp.concatenate([rhs, jnp.cross(Pi, om) + M_R])
        if self.string_forces:
            rhs = rhs + self.string_force(t, x, w)
        if self.body_loads:
            rhs = rhs + self.body_load(t, x, R, w)
        return jnp.linalg.solve(M, rhs - Mdot_w)

    # ------------------------------------------------------------------------------------
    # Quaternion ODE state for the baselines
    # ------------------------------------------------------------------------------------
    def split_state(self, y):
        """y -> (x, R(quat), w, W); R(quat) is not renormalised."""
        lay = self.layout
        x, w = y[lay.y_x], y[lay.y_w]
        R = quat_to_rot(y[lay.y_quat]) if lay.has_attitude else jnp.eye(3)
        W = y[lay.y_work][0] if lay.has_work else jnp.asarray(0.0)
        return x, R, w, W

    def ode_rhs(self, t, y):
        lay = self.layout
        x, R, w, _ = self.split_state(y)
        parts = [w[: lay.nx]]
        if lay.has_attitude:
            parts.append(quat_rate(y[lay.y_quat], self.omega(w)))
        parts.append(self.accelerations(t, x, R, w))
        if lay.has_work:
            parts.append(jnp.atleast_1d(self.power(t, x, w, R)))
        return jnp.concatenate(parts)

    # ------------------------------------------------------------------------------------
    # Initial state: a straight string along `direction`, stretched by `initial.stretch`
    # ------------------------------------------------------------------------------------
    def initial_state(self):
        """(x0, R0, w0) as numpy arrays.

        The string is straight along ``initial.direction``, uniformly stretched by
        ``initial.stretch`` (stretched / unstretched length; 1 = unstretched, < 1 compressed).
        """
        ini, lay = self.scene.initial, self.layout
        ell0 = ini.deployed_length
        a = np.arange(2, self.N + 2, dtype=float)  # nodes 2 .. N+1
        q = ((a - 1) / self.N * ell0 * ini.stretch)[:, None] * np.array(ini.direction)[None, :]
        qd = ((a - 1) / self.N)[:, None] * np.array(ini.tip_velocity)[None, :]
        x = np.concatenate([[self.L - ell0] if lay.has_reel else [], q.ravel()])
        w = np.concatenate([[ini.reel_rate] if lay.has_reel else [], qd.ravel(),
                            ini.angular_velocity if lay.has_attitude else []])
        R = np.array(ini.attitude) if lay.has_attitude else np.eye(3)
        return x, R, w

    def initial_ode_state(self) -> np.ndarray:
        x, R, w = self.initial_state()
        lay = self.layout
        return np.concatenate([x, rot_to_quat(R) if lay.has_attitude else [], w, [0.0] if lay.has_work else []])

    # ------------------------------------------------------------------------------------
    # Compiled entry points (cached per model)
    # ------------------------------------------------------------------------------------
    @functools.cached_property
    def ode_rhs_jit(self):
        return jax.jit(self.ode_rhs)

    @functools.cached_property
    def ode_jacobian_jit(self):
        return jax.jit(jax.jacfwd(self.ode_rhs, argnums=1))


@functools.lru_cache(maxsize=64)
def build_model(scene: Scene) -> StringPendulum:
    """The model of a scene (cached, so compiled functions are shared between users)."""
    return StringPendulum(scene)
