"""Physical effects as objects: each effect in one place (models/README.md, "Adding an effect").

A scene lists effects by name; `EFFECTS` maps each name to an `Effect`, in canonical order.
An effect declares everything it contributes, and nothing else needs to know its name:

* scene format (`models.schema`): the keys it owns (`keys`), their plausible magnitudes
  (`plausible`), the effects it needs (`needs`) and its own cross-checks (`check`, which
  receives the public `models.schema.SceneChecks`);
* state layout (`models.layout`): coordinates it adds (`state`) and whether it does
  non-conservative work (`forcing`, which puts W in the ODE state);
* physics (`models.model.StringPendulum`, assembled once per scene): potential terms with
  their closed-form gradients (`potentials`), reel forces on s_p (`reel_forces`), string
  forces over w's layout (`string_forces`), loads on the body that may turn it (`body_loads`:
  a moment in the body frame and forces that depend on the attitude), a change of the elastic
  law (`elastic_law`), its share of the energy scale (`energy_scale`) and the power its forces
  claim (`power`, `body_power`; checked by the tests and `benchmark.contract.verify`).

The integrators read only the model's totals (`potential_gradient`, `reel_force`,
`string_force`, `body_load`, `generalized_force`, `potential`, `kinetic`), so a new potential or force
needs no integrator edit. An effect is added at run time by `register_effect`, or by an
installed package through the entry-point group `reelbench.effects` (`ENTRY_POINT_GROUP`),
loaded the first time a scene is validated, in every process (the benchmark's workers too).

The kinetic energy is not an effect's to change: the closed form (`models.closed_form`) and
the LGVI derive the string's, the body's and the reel's kinetic energy themselves, so an
added effect that overrides `kinetic` would be honoured by the autodiff path only. Such an
effect is refused when it is registered, with that reason.

No JAX at import: scenes are validated before JAX is loaded (the command line refuses bad
input fast), so the physics hooks import `models._jax` when they are called.
"""

from __future__ import annotations

import re
from importlib.metadata import entry_points
from typing import Callable, NamedTuple

import numpy as np

from reelbench.models.origin import of_distribution as origin_of_distribution, of_object as origin_of_object, project_origin
from reelbench.models.schema import BASE_SCHEMA, GYRATION_RADIUS, Key, SceneChecks

E3 = np.array([0.0, 0.0, 1.0])

#: Entry-point group of effect plugins: ``name = "package.module:EffectClass"`` (or an instance).
ENTRY_POINT_GROUP = "reelbench.effects"

#: An effect's name is a TOML section name and a keyword of `load_scene`.
EFFECT_NAME = re.compile(r"[a-z][a-z0-9_]{0,63}")

__all__ = ["EFFECTS", "ENTRY_POINT_GROUP", "Effect", "Key", "PotentialTerm", "SceneChecks", "effect_keys",
           "effect_origin", "get_effect", "load_plugins", "plugin_errors", "register_effect", "unregister_effect", "unusable"]


class PotentialTerm(NamedTuple):
    """V(x, R) and its closed-form gradient over w's layout (∂V/∂s_p, ∂V/∂q, ∂V/∂η).

    ∂V/∂η is the derivative along R(I + η^). The tests check ``gradient`` against autodiff of
    ``energy`` for every registered effect (tests/test_effects.py).
    """

    energy: Callable
    gradient: Callable


class Effect:
    """One physical effect. Subclass, set the class attributes, override the hooks you need.

    Every physics hook takes the `StringPendulum` being built (parameters and kinematics
    live there: ``model.nodes``, ``model.element_length``, ``model.over_w`` …) and returns
    functions of the state; a hook an effect does not override contributes nothing.
    """

    name: str = ""
    needs: tuple[str, ...] = ()
    #: a string is not a model without it (`elasticity`)
    required: bool = False
    #: coordinates this effect adds to the state: "s_p" (the reel), "attitude" (R, Ω)
    state: tuple[str, ...] = ()
    #: adds non-conservative generalized forces: their work W is carried in the ODE state
    forcing: bool = False
    #: its forces never add energy (power ≤ 0; checked by the tests)
    dissipative: bool = False
    #: its energy and forces are symmetric about the vertical through the reel, so π3 (the
    #: angular momentum about it) stays conserved: internal forces, gravity, forces on the reel
    #: coordinate. Not declared (a drag, a spring to an anchor off that axis): π3 is not reported
    #: (`pi3_error` empty) nor plotted for a scene that lists it.
    conserves_pi3: bool = False
    #: its terms vanish when it is not listed (its numbers are then 0) and it adds no state: a
    #: model that could take it without a new coordinate compiles it in, with those zeros, so that
    #: scenes with and without it share compiled programs (`StringPendulum.structure_key`)
    zero_when_unlisted: bool = False
    #: scene keys it owns: {section: {key: Key}} ("" for a top-level key)
    keys: dict[str, dict[str, Key]] = {}
    #: plausible magnitudes of its keys, {"section.key": (low, high)} (see `models.scene.PLAUSIBLE`)
    plausible: dict[str, tuple[float, float]] = {}
    #: one line for the README's table and error messages
    summary: str = ""

    # -- scene rules ----------------------------------------------------------------------
    def check(self, checks: SceneChecks, d: dict, effects: tuple[str, ...]) -> None:
        """Cross-checks of the validated scene dict ``d`` ({section: {key: value}}, defaults
        filled in), run for every registered effect, listed or not (``self.name in effects``).
        Refuse with ``raise checks.fail(key, value, allowed)`` or ``raise checks.refuse(message)``
        (`models.schema.SceneChecks`). A key of this effect given with a value other than its
        default while the effect is not listed is refused before this runs."""

    # -- physics --------------------------------------------------------------------------
    def kinetic(self, model) -> dict[str, Callable]:
        """{name: T(x, R, w)}; a name already present (e.g. "T_body") is replaced.

        Built-in effects only (`reel`, `rigid_body`): the closed form and the LGVI have these
        terms written out, so `register_effect` refuses an effect that overrides this hook.
        """
        return {}

    def potentials(self, model) -> dict[str, PotentialTerm]:
        return {}

    def reel_forces(self, model) -> dict[str, Callable]:
        """{name: Q(t, x, w)}, scalar forces on s_p that depend on w only through ṡ_p."""
        return {}

    def string_forces(self, model) -> dict[str, Callable]:
        """{name: Q(t, x, w)}, vectors over w's layout acting on (s_p, q), not on Ω."""
        return {}

    def body_loads(self, model) -> dict[str, Callable]:
        """{name: Q(t, x, R, w)}, vectors over w's layout that may act on the body's rotation and
        depend on its attitude R and angular velocity Ω: the Ω slot is a moment on the body about
        the attachment point, in the body frame (N m), ``model.over_w(deta=M)``; a force f
        (inertial frame) at the body point ρ (body frame, from the attachment point) is
        ``model.over_w(dq=f on the last node, deta=ρ × Rᵀ f)``. Only with `rigid_body` (a
        point-mass scene has no Ω slot: `over_w` drops the moment). Its power Q·w includes Ω·M;
        give it in closed form in `body_power`."""
        return {}

    def elastic_law(self, model) -> tuple[Callable, Callable] | None:
        """(taut_length(stretch, l), clip_tension(tension)) replacing the two-sided law, or None."""
        return None

    def energy_scale(self, model) -> float:
        """The most energy this effect can supply over the run beyond T(0) + Σ|V(0)| (J)."""
        return 0.0

    def power(self, model, t, x, w):
        """Q·w of this effect's reel and string forces in closed form (None: no forces)."""
        return None

    def body_power(self, model, t, x, R, w):
        """Q·w of this effect's body loads in closed form, Ω·M included (None: no body loads)."""
        return None

    def __repr__(self) -> str:
        return f"<effect {self.name!r}>"


# --------------------------------------------------------------------------------------------
# The built-in effects (models/README.md, "Effects")
# --------------------------------------------------------------------------------------------


def _weight_terms(m, per_length, body):
    """The potential of a uniform vertical load on the deployed string and a point load at the
    body's centre of mass: per_length (N/m, along +e3) on each element at its midpoint (exact for
    linear elements), body (N) at r_p + q_{N+1} (+ R ρ_c). Gravity's weights (μ g, m_b g) and
    buoyancy's (−ρ_f g A, −ρ_f g V) are this one formula with their own signs."""
    from reelbench.models._jax import jnp

    e3 = jnp.asarray(E3)

    def V_string(x, R):
        q, l = m.nodes(x), m.element_length(x)
        mid = m.r_p + 0.5 * (q[:-1] + q[1:])  # each element at its midpoint
        return -per_length * l * jnp.sum(mid[:, 2])

    # node N+1 ends one element only: weight ½ (a constant, so it is not rebuilt per call)
    weights_e3 = np.outer(np.r_[np.ones(m.N - 1), 0.5], E3)

    def dV_string(x, R):
        q, l = m.nodes(x), m.element_length(x)
        dq = -(per_length * l) * jnp.asarray(weights_e3)
        # l = (L − s_p)/N: ∂V/∂s_p = w Σ mid_z / N
        ds = jnp.sum(per_length * (2 * m.r_p[2] + q[:-1, 2] + q[1:, 2])) / (2 * m.N) if m.layout.has_reel else None
        return m.over_w(ds=ds, dq=dq)

    def V_body(x, R):
        tip = m.r_p + m.nodes(x)[-1]
        if m.layout.has_attitude:
            tip = tip + R @ m.rho_c
        return -body * tip[2]

    tip_row = np.zeros((m.N, 1))
    tip_row[-1] = 1.0  # structural; the load itself may be a run-time value (`StringPendulum.bind`)

    def dV_body(x, R):
        # the negative moment of the load about the attachment point
        deta = -body * jnp.cross(m.rho_c, R.T @ e3) if m.layout.has_attitude else None
        return m.over_w(dq=jnp.asarray(tip_row) * (-body * e3)[None, :], deta=deta)

    return PotentialTerm(V_string, dV_string), PotentialTerm(V_body, dV_body)


def _reach(m) -> float:
    """The largest height difference the string and the body can span (energy scales)."""
    return m.L + float(np.linalg.norm(m.rho_c)) + float(np.linalg.norm(m.r_d)) + m.d


class Gravity(Effect):
    name = "gravity"
    conserves_pi3 = True
    summary = "potential of the string, the body and the reel-side string (g along +e3)"

    def potentials(self, m):
        from reelbench.models._jax import jnp

        string, body = _weight_terms(m, m.mu * m.g, m.m_b * m.g)
        terms = {"V_string_gravity": string, "V_body_gravity": body}
        if m.layout.has_reel:
            def V_reel(x, R):
                """Reel-side string: the part stored on the drum and in the guide way."""
                s = x[0]
                return -m.mu * m.g * s * m.r_d[2] - m.mu * m.g * m.d**2 * jnp.cos((s - m.b) / m.d)

            def dV_reel(x, R):
                s = x[0]
                return m.over_w(ds=-m.mu * m.g * m.r_d[2] + m.mu * m.g * m.d * jnp.sin((s - m.b) / m.d))

            terms["V_reel"] = PotentialTerm(V_reel, dV_reel)
        return terms

    def energy_scale(self, m):
        # the most potential energy gravity could release over the whole string length
        return m.g * (m.m_b + m.mu * m.L) * _reach(m)


class Elasticity(Effect):
    name = "elasticity"
    conserves_pi3 = True
    required = True
    summary = "axial strain energy (EA/2l)(stretched length − l)² of every element"

    def potentials(self, m):
        from reelbench.models._jax import jax, jnp

        def V(x, R):
            """Σ_a (EA/2l)(|q_{a+1} − q_a| − l)², or with `slack` Σ_a (EA/2l) max(|q_{a+1} − q_a| − l, 0)²."""
            _, stretch, l = m.elements(x)
            taut = m._taut_length(stretch, l)
            return jnp.sum(m.EA / (2 * l) * (taut - l) ** 2)

        def dV(x, R):
            delta, stretch, l = m.elements(x)
            taut = m._taut_length(stretch, l)  # = stretch, or max(stretch, l) with `slack`
            grad_e = (m.EA / l * (taut - l) / stretch)[:, None] * delta  # ∇V^e_a, a = 1..N
            dq = jax.lax.dynamic_update_slice(grad_e, grad_e[:-1] - grad_e[1:], (0, 0))  # nodes 2..N+1
            ds = jnp.sum(m.EA / l**2 * (taut**2 - l**2)) / (2 * m.N)
            return m.over_w(ds=ds, dq=dq)

        return {"V_elastic": PotentialTerm(V, dV)}


class RigidBody(Effect):
    name = "rigid_body"
    conserves_pi3 = True
    state = ("attitude",)
    summary = "attitude R and angular velocity Ω as state; inertia J_c and offset ρ_c"
    keys = {
        "body": {
            "box": Key("vec3", "positive"),
            "inertia": Key("mat3", "spd"),
            "attachment_to_com": Key("vec3", default=(0.0, 0.0, 0.0)),
        },
        "initial": {
            "attitude": Key("mat3", "rotation", default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))),
            "angular_velocity": Key("vec3", default=(0.0, 0.0, 0.0)),
        },
    }
    plausible = {"body.box": (1e-6, 1e4), "body.attachment_to_com": (0.0, 1e4), "initial.angular_velocity": (0.0, 1e5)}

    def check(self, checks, d, effects):
        b = d["body"]
        if self.name not in effects:
            return
        if b["box"] is not None and b["inertia"] is not None:
            raise checks.refuse("keys 'body.box' and 'body.inertia' are alternatives: give one")
        if b["box"] is None and b["inertia"] is None:
            raise checks.refuse("missing key 'body.box' or 'body.inertia' (needed by effect rigid_body)")
        key = "body.box" if b["box"] is not None else "body.inertia"
        moments = np.linalg.eigvalsh(body_inertia(b))
        # roots first: moments near 1e308 over a mass of 1e-9 kg would overflow the quotient
        radius = np.sqrt(np.maximum(moments, 0.0)) / np.sqrt(b["mass"])
        lo, hi = GYRATION_RADIUS
        if not (lo <= radius.min() and radius.max() <= hi):
            raise checks.refuse(
                f"key '{key}' = {b[key.split('.')[1]]} is implausible: allowed principal moments of inertia "
                f"whose radius of gyration sqrt(J/m_b) is in [{lo:g}, {hi:g}] m (m_b = body.mass = {b['mass']:g} kg; "
                f"these give {radius.min():.3g} ... {radius.max():.3g} m). Check the units and the exponent", key)
        # every real body's principal moments satisfy J1 <= J2 + J3 (and the LGVI's J_d is
        # positive definite only then)
        if 2.0 * moments.max() > moments.sum() * (1.0 + 1e-12):
            raise checks.fail(key, b[key.split(".")[1]],
                              f"an inertia whose principal moments satisfy J1 <= J2 + J3, as every real body's do "
                              f"(these are {', '.join(f'{x:.6g}' for x in moments)} kg m^2)")

    def kinetic(self, m):
        return {"T_body": m._T_rigid_body}  # replaces the point mass's T_body


class Reel(Effect):
    name = "reel"
    conserves_pi3 = True
    state = ("s_p",)
    summary = "s_p as a coordinate: drum and reel-side inertia, axial-flow coupling"
    keys = {
        "reel": {
            "radius": Key("float", "positive", required_by=("reel",), default=1.0, kept_without_effect=True),
            "center": Key("vec3", required_by=("reel",), default=(0.0, 0.0, 0.0), kept_without_effect=True),
            "guide_length": Key("float", "positive", required_by=("reel",), default=0.0, kept_without_effect=True),
            "equivalent_mass": Key("float", "positive", required_by=("reel",), default=1.0, kept_without_effect=True),
        },
        "initial": {"reel_rate": Key("float", default=0.0)},
    }
    plausible = {"reel.radius": (1e-6, 1e4), "reel.center": (0.0, 1e5), "reel.guide_length": (0.0, 1e5),
                 "reel.equivalent_mass": (1e-9, 1e9), "initial.reel_rate": (0.0, 1e4)}

    def check(self, checks, d, effects):
        if self.name in effects and d["string"]["mass_model"] == "lumped":
            # the lumped string's axial-flow terms (its M0 and M31/M23) are not derived
            raise checks.refuse(
                "key 'string.mass_model' = 'lumped' is not available with effect 'reel': allowed 'consistent' "
                "with a reel (the lumped string's axial-flow terms are not derived); 'lumped' needs a "
                "fixed-length scene", "string.mass_model")

    def kinetic(self, m):
        return {"T_reel": m._T_reel}


class Carnot(Effect):
    name = "carnot"
    conserves_pi3 = True
    needs = ("reel",)
    forcing = True
    dissipative = True
    summary = "Carnot loss of the velocity jump at the guide-way exit (a force on s_p)"

    def reel_forces(self, m):
        return {"Q_carnot": lambda t, x, w: self._jump_force(m, x, w)}

    @staticmethod
    def _jump_force(m, x, w):
        """Q_c = -½ μ ṡ|ṡ| |q_2/l − t_g|², so Q_c ṡ = -½ μ |ṡ|³ |q_2/l − t_g|² ≤ 0."""
        from reelbench.models._jax import jnp

        sd = w[0]
        jump = m.nodes(x)[1] / m.element_length(x) - m.t_g
        return -0.5 * m.mu * sd * jnp.abs(sd) * (jump @ jump)

    def power(self, m, t, x, w):
        from reelbench.models._jax import jnp

        jump = m.nodes(x)[1] / m.element_length(x) - m.t_g
        return -0.5 * m.mu * jnp.abs(w[0]) ** 3 * (jump @ jump)


class ReelControl(Effect):
    name = "reel_control"
    conserves_pi3 = True
    needs = ("reel",)
    forcing = True
    summary = "constant drum moment u (reel.control_moment) as the force u/d on s_p"
    #: unlisted, u = 0 and its force vanishes: a scene with the reel's work W in its state shares
    #: its compiled programs with the same scene driven by a moment (`StringPendulum.structure_key`)
    zero_when_unlisted = True
    keys = {"reel": {"control_moment": Key("float", default=0.0)}}
    plausible = {"reel.control_moment": (0.0, 1e12)}

    def reel_forces(self, m):
        from reelbench.models._jax import jnp

        return {"Q_control": lambda t, x, w: jnp.asarray(m.u / m.d)}

    def energy_scale(self, m):
        # the most work the constant moment can do over the whole string length
        return abs(m.u) * m.L / m.d

    def power(self, m, t, x, w):
        return m.u / m.d * w[0]


def _tension_only(stretch, l):
    """Elastic length of a tension-only element: max(stretch, l), no energy when shorter."""
    from reelbench.models._jax import jnp

    return jnp.maximum(stretch, l)


def _clip_compression(tension):
    from reelbench.models._jax import jnp

    return jnp.maximum(tension, 0.0)


class Slack(Effect):
    name = "slack"
    conserves_pi3 = True
    needs = ("elasticity",)
    summary = "tension-only elasticity: max(stretch − l, 0) in V_elastic; tensions clipped at 0"

    def elastic_law(self, m):
        # max(|q_{a+1} − q_a|, l): V_e, its gradient and the tensions all get max(|Δq| − l, 0)
        return _tension_only, _clip_compression


class AxialDamping(Effect):
    name = "axial_damping"
    conserves_pi3 = True
    needs = ("elasticity",)
    forcing = True
    dissipative = True
    summary = "Kelvin–Voigt damping c ε̇ of each element's strain rate (string.axial_damping = c)"
    keys = {"string": {"axial_damping": Key("float", "nonnegative", required_by=("axial_damping",),
                                            only_with_effect=True)}}
    plausible = {"string.axial_damping": (0.0, 1e12)}

    def string_forces(self, m):
        from reelbench.models._jax import jnp

        def Q(t, x, w):
            """Kelvin–Voigt strain-rate damping: Q = −∂D/∂w, D = Σ_a (c l/2) ε̇_a² (Rayleigh).

            Element a carries the damping tension τ_a = c ε̇_a along ê_a = (q_{a+1} − q_a)/|q_{a+1} − q_a|:
            it pulls node a by +τ_a ê_a and node a+1 by −τ_a ê_a; on s_p (through l) it gives
            −Σ_a τ_a |q_{a+1} − q_a| / (N l). The dashpot acts in compression too (also with
            `slack`), which keeps Q smooth in the state.
            """
            delta, stretch, l = m.elements(x)
            tau = m.axial_damping * m.strain_rates(x, w)
            f = (tau / stretch)[:, None] * delta  # τ_a ê_a, a = 1..N
            fq = jnp.concatenate([f[1:], jnp.zeros((1, 3))], axis=0) - f  # nodes 2..N+1
            return m.over_w(ds=-jnp.sum(tau * stretch) / (m.N * l), dq=fq)

        return {"Q_axial_damping": Q}

    def power(self, m, t, x, w):
        from reelbench.models._jax import jnp

        rate = m.strain_rates(x, w)
        return -jnp.sum(m.axial_damping * m.element_length(x) * rate * rate)


class Buoyancy(Effect):
    """The weight of the displaced fluid, upward (−e3): on every element of the deployed string
    through its volume-equivalent diameter d (ρ_f g π d²/4 per unstretched length, at the
    element's midpoint like gravity) and on the body through its volume V (at its centre of
    mass: a homogeneous body's centre of buoyancy). The deployed string and the body are taken
    as wholly immersed; the reel and the guide way are not."""

    name = "buoyancy"
    needs = ("gravity",)
    summary = "weight of the displaced fluid (fluid.density), upward: string by string.diameter, body by body.volume"
    keys = {
        "fluid": {"density": Key("float", "positive", required_by=("buoyancy",), only_with_effect=True)},
        "string": {"diameter": Key("float", "positive", required_by=("buoyancy",), only_with_effect=True)},
        "body": {"volume": Key("float", "nonnegative", default=0.0, only_with_effect=True)},
    }
    plausible = {"fluid.density": (1e-6, 1e5), "string.diameter": (1e-6, 1e2), "body.volume": (1e-12, 1e9)}

    @staticmethod
    def displaced_per_length(scene) -> float:
        """ρ_f π d²/4: the fluid mass the string displaces per unstretched length, kg/m."""
        return scene.section("fluid")["density"] * np.pi * scene.string.diameter ** 2 / 4.0

    @staticmethod
    def floats_note(scene) -> str | None:
        """A note when the string is lighter than the fluid it displaces (allowed: it floats)."""
        if not scene.has("buoyancy"):
            return None
        displaced = Buoyancy.displaced_per_length(scene)
        if scene.string.mass_per_length >= displaced:
            return None
        return (f"the string floats: string.mass_per_length = {scene.string.mass_per_length:g} kg/m is less than "
                f"the {displaced:g} kg/m of fluid it displaces (fluid.density x pi string.diameter^2 / 4); its net "
                "weight points up, so without a heavy enough body it rises")

    def check(self, checks, d, effects):
        if self.name not in effects:
            return
        displaced = d["fluid"]["density"] * np.pi * d["string"]["diameter"] ** 2 / 4.0
        if d["string"]["mass_per_length"] < displaced:
            import warnings

            warnings.warn(f"{checks.source}: the string floats: string.mass_per_length = "
                          f"{d['string']['mass_per_length']:g} kg/m < {displaced:g} kg/m of displaced fluid "
                          "(allowed; its net weight points up)", FloatingStringWarning, stacklevel=2)

    def potentials(self, m):
        rho = m.fluid_density
        string, body = _weight_terms(m, -rho * m.g * np.pi * m.string_diameter ** 2 / 4.0,
                                     -rho * m.g * m.body_volume)
        return {"V_string_buoyancy": string, "V_body_buoyancy": body}

    def energy_scale(self, m):
        rho = m.fluid_density
        volume = np.pi * m.string_diameter ** 2 / 4.0 * m.L + m.body_volume
        return m.g * rho * volume * _reach(m)


class FloatingStringWarning(UserWarning):
    """A scene's string is lighter than the fluid it displaces (allowed: it floats)."""


#: 3-point Gauss–Legendre rule on [0, 1] (exact for polynomials of degree 5): the drag of the
#: finite-element string, a smooth but non-polynomial load, integrated over each element
GAUSS_POINTS = 0.5 + 0.5 * np.sqrt(0.6) * np.array([-1.0, 0.0, 1.0])
GAUSS_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 18.0


def _norm(v):
    """|v| along the last axis, with derivative 0 (not NaN) at v = 0: |v| v is differentiable there."""
    from reelbench.models._jax import jnp

    vv = jnp.sum(v * v, axis=-1)
    pos = vv > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, vv, 1.0)), 0.0)


class Drag(Effect):
    """Morison drag, quadratic in the velocity relative to a uniform current U (`fluid.current`).

    On the string, per unstretched length, with t the unit tangent and u = U − v split into
    u_t = (u·t) t and u_n = u − u_t: f = ½ ρ_f d (C_n |u_n| u_n + π C_t |u_t| u_t) (MoorDyn v2's
    definitions, the π of the tangential term included: C_t refers to the wetted perimeter π d).
    The lumped string (`string.mass_model = "lumped"`) takes it per node as MoorDyn does: the
    node's velocity, the tangent (q_{a+1} − q_{a−1})/|…| at interior nodes and that of the
    adjacent element at the ends, over half the unstretched length of the elements on either
    side. The finite-element string integrates f over each element by `GAUSS_POINTS` with its
    linear shape functions, at the material velocity (with a reel the material slides through
    the nodes: v = (1−ξ) v_a + ξ v_{a+1} + Δ_a ṡ_p ((a−1+ξ)/N − 1)/l, the same axial flow as in
    the kinetic energy), and gives s_p its share ∫ f·∂r/∂s_p. On the body, at its centre of
    mass: f_b = ½ ρ_f (C_d A) |U − v_c| (U − v_c) with v_c the velocity of the centre of mass. A
    rigid body whose centre of mass is offset from the attachment point (ρ_c ≠ 0) takes it as a
    body load (`Effect.body_loads`): v_c = q̇_{N+1} + R (Ω × ρ_c), f_b on the last node and its
    moment about the attachment point, ρ_c × Rᵀ f_b (body frame), on the rotation; the body has
    no rotational drag of its own (a damper effect adds one: models/README.md). Otherwise (no
    offset, or a point mass) v_c = q̇_{N+1} and f_b is part of the string force. With a current
    the fluid can do positive work, so the effect does not claim to be dissipative."""

    name = "drag"
    needs = ("buoyancy",)
    forcing = True
    summary = "Morison drag on the string (string.normal_drag, tangential_drag) and the body (body.drag_area)"
    keys = {
        "fluid": {"current": Key("vec3", default=(0.0, 0.0, 0.0), only_with_effect=True)},
        "string": {"normal_drag": Key("float", "nonnegative", required_by=("drag",), only_with_effect=True),
                   "tangential_drag": Key("float", "nonnegative", required_by=("drag",), only_with_effect=True)},
        "body": {"drag_area": Key("float", "nonnegative", default=0.0, only_with_effect=True)},
    }
    plausible = {"fluid.current": (0.0, 1e3), "string.normal_drag": (1e-6, 1e3), "string.tangential_drag": (1e-6, 1e3),
                 "body.drag_area": (1e-12, 1e6)}

    # -- the pieces ---------------------------------------------------------------------------
    @staticmethod
    def _params(m):
        half_rho = 0.5 * m.fluid_density
        return (half_rho * m.string_diameter * m.normal_drag, half_rho * m.string_diameter * np.pi * m.tangential_drag,
                half_rho * m.drag_area, m.current)

    @staticmethod
    def _morison(kn, kt, u, t):
        """kn |u_n| u_n + kt |u_t| u_t for relative velocities u and unit tangents t (…, 3)."""
        from reelbench.models._jax import jnp

        ut = jnp.sum(u * t, axis=-1, keepdims=True) * t
        un = u - ut
        return kn * _norm(un)[..., None] * un + kt * _norm(ut)[..., None] * ut

    def _element_loads(self, m, x, w):
        """FE string: per Gauss point g, (f_g (N, 3) per unstretched length, material velocity v_g
        (N, 3), ∂r/∂s_p β_g Δ (N, 3) or None)."""
        from reelbench.models._jax import jnp

        kn, kt, _, U = self._params(m)
        q, v, l = m.nodes(x), m.node_velocities(w), m.element_length(x)
        delta = q[1:] - q[:-1]
        t = delta / _norm(delta)[:, None]
        a = np.arange(1, m.N + 1, dtype=float)
        out = []
        for xi in GAUSS_POINTS:
            vg = (1.0 - xi) * v[:-1] + xi * v[1:]
            ds_dir = None
            if m.layout.has_reel:
                # a material point at (a−1+ξ) l from the exit moves along the element as s_p changes
                ds_dir = jnp.asarray(((a - 1.0 + xi) / m.N - 1.0))[:, None] * delta / l
                vg = vg + ds_dir * m.reel_rate(w)
            out.append((self._morison(kn, kt, jnp.asarray(U) - vg, t), vg, ds_dir))
        return out

    def _node_loads(self, m, x, w):
        """Lumped string (MoorDyn's nodes): forces on nodes 2 … N+1 (N, 3) and their velocities."""
        from reelbench.models._jax import jnp

        kn, kt, _, U = self._params(m)
        q, v, l = m.nodes(x), m.node_velocities(w), m.element_length(x)
        ahead = jnp.concatenate([q[2:], q[-1:]], axis=0)  # q_{a+1}, a = 2 … N+1 (q_{N+1} at the end)
        t = ahead - q[:-1]  # q_{a+1} − q_{a−1}; at node N+1: q_{N+1} − q_N
        t = t / _norm(t)[:, None]
        length = jnp.asarray(np.r_[np.ones(m.N - 1), 0.5])[:, None] * l  # half of each adjacent element
        vn = v[1:]
        return length * self._morison(kn, kt, jnp.asarray(U) - vn, t), vn

    def _body_load(self, m, w):
        _, _, kb, U = self._params(m)
        u = U - m.node_velocities(w)[-1]
        return kb * _norm(u) * u

    @staticmethod
    def _offset(m) -> bool:
        """The body's drag is a body load: a rigid body with ρ_c ≠ 0 and a drag area."""
        return m.drag_at_offset  # decided from the host values when the model is built

    def _com_load(self, m, R, w):
        """(f_b, v_c): the drag at the centre of mass of an offset body and that point's velocity."""
        from reelbench.models._jax import jnp

        _, _, kb, U = self._params(m)
        v = m.node_velocities(w)[-1] + R @ jnp.cross(m.omega(w), m.rho_c)
        u = U - v
        return kb * _norm(u) * u, v

    # -- the hooks ----------------------------------------------------------------------------
    def string_forces(self, m):
        from reelbench.models._jax import jnp

        lumped = m.scene.string.mass_model == "lumped"
        offset = self._offset(m)

        def Q(t, x, w):
            """Drag as a generalized force: on the nodes (and s_p) by the virtual work ∫ f·δr."""
            if lumped:
                fq, _ = self._node_loads(m, x, w)
                ds = None
            else:
                l = m.element_length(x)
                left = right = 0.0
                ds = 0.0
                for wg, xi, (f, _, ds_dir) in zip(GAUSS_WEIGHTS, GAUSS_POINTS, self._element_loads(m, x, w)):
                    left = left + (wg * (1.0 - xi) * l) * f
                    right = right + (wg * xi * l) * f
                    if ds_dir is not None:
                        ds = ds + wg * l * jnp.sum(ds_dir * f)
                # node b = 2 … N+1 ends element b−1 (right share) and starts element b (left share)
                fq = right + jnp.concatenate([left[1:], jnp.zeros((1, 3))], axis=0)
                ds = ds if m.layout.has_reel else None
            if not offset:
                fq = fq.at[-1].add(self._body_load(m, w))
            return m.over_w(ds=ds, dq=fq)

        return {"Q_drag": Q}

    def body_loads(self, m):
        from reelbench.models._jax import jnp

        if not self._offset(m):
            return {}
        tip = np.zeros((m.N, 1))
        tip[-1] = 1.0

        def Q(t, x, R, w):
            """f_b at the centre of mass: f_b on node N+1, ρ_c × Rᵀ f_b on the rotation."""
            f, _ = self._com_load(m, R, w)
            return m.over_w(dq=jnp.asarray(tip) * f[None, :], deta=jnp.cross(m.rho_c, R.T @ f))

        return {"Q_drag_body": Q}

    def body_power(self, m, t, x, R, w):
        """f_b·v_c (offset body only)."""
        if not self._offset(m):
            return None
        f, v = self._com_load(m, R, w)
        return f @ v

    def power(self, m, t, x, w):
        """∫ f·v over the string (the same quadrature, at the material velocity) + f_body·v_body."""
        from reelbench.models._jax import jnp

        if m.scene.string.mass_model == "lumped":
            f, v = self._node_loads(m, x, w)
            P = jnp.sum(f * v)
        else:
            l = m.element_length(x)
            P = sum(wg * l * jnp.sum(f * vg) for wg, (f, vg, _) in zip(GAUSS_WEIGHTS, self._element_loads(m, x, w)))
        if self._offset(m):  # the body's share is `body_power`
            return P
        return P + self._body_load(m, w) @ m.node_velocities(w)[-1]

    def energy_scale(self, m):
        # what a current can give the string and the body: twice their kinetic energy at its speed
        U = np.asarray(m.current, dtype=float)
        return (m.m_b + m.mu * m.L) * float(U @ U)


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

#: Every effect a scene may list, by name, in canonical order (the order of `Scene.effects`,
#: hence of `Scene.key()`: append new effects, never reorder).
EFFECTS: dict[str, Effect] = {}


#: The hooks' key kinds, and the rules each kind knows (`models.schema.Validator`).
_KEY_RULES = {"float": {"finite", "positive", "nonnegative", "stretch"}, "int": {"finite", "at_least_1"},
              "str": {"finite", "line", "name"}, "vec3": {"finite", "positive", "nonzero"}, "mat3": {"spd", "rotation"}}

_KINETIC_REFUSED = ("it overrides Effect.kinetic, which an added effect may not: the closed form "
                    "(models.closed_form) and the LGVI write the kinetic energy of the string, the body and the "
                    "reel out themselves and would ignore the change, so only the autodiff path would see it; "
                    "an added effect contributes potentials (with their gradients) and forces")


def _overrides_kinetic(effect: Effect) -> bool:
    return type(effect).kinetic is not Effect.kinetic


def register_effect(effect: Effect | type[Effect]) -> Effect:
    """Add ``effect`` (an `Effect` instance, or an `Effect` subclass, instantiated without
    arguments) to the registry (at the end of the canonical order); returns the instance.

    Its scene keys become valid at once (scenes are validated against the registry as it is
    when they are loaded); a model built afterwards composes its terms. Refused (ValueError,
    with the reason): a name that is not a lower-case identifier, a name or scene key already
    taken, a need not registered, a key kind or rule the schema does not know, a plausible
    range for a key the effect does not own, and an override of `Effect.kinetic`.
    """
    if isinstance(effect, type) and issubclass(effect, Effect):
        effect = effect()
    if not isinstance(effect, Effect) or not effect.name:
        raise TypeError(f"register_effect needs an Effect subclass or instance with a name, not {effect!r}")
    if not isinstance(effect.name, str) or not EFFECT_NAME.fullmatch(effect.name):
        raise ValueError(f"effect name {effect.name!r} is invalid: allowed a lower-case identifier "
                         f"({EFFECT_NAME.pattern}; it names a TOML section and a keyword)")
    if effect.name in EFFECTS:
        raise ValueError(f"effect {effect.name!r} is already registered")
    for need in effect.needs:
        if need not in EFFECTS:
            raise ValueError(f"effect {effect.name!r} needs {need!r}, which is not registered")
    if _overrides_kinetic(effect):
        raise ValueError(f"effect {effect.name!r} is refused: {_KINETIC_REFUSED}")
    _check_keys(effect)
    EFFECTS[effect.name] = effect
    return effect


def _check_keys(effect: Effect) -> None:
    owned = {(s, k) for e in EFFECTS.values() for s, sec in e.keys.items() for k in sec}
    mine = set()
    for section, sec in effect.keys.items():
        base_section = BASE_SCHEMA.get(section)
        if section and base_section is not None and not isinstance(base_section, dict):
            raise ValueError(f"effect {effect.name!r}: section [{section}] is a top-level scene key")
        for key, spec in sec.items():
            dotted = f"{section}.{key}" if section else key
            base = base_section if section else BASE_SCHEMA.get(key)
            if (section, key) in owned or (isinstance(base, dict) and key in base) or (not section and base):
                raise ValueError(f"effect {effect.name!r}: scene key '{dotted}' is already defined")
            if not isinstance(spec, Key) or spec.rule not in _KEY_RULES.get(spec.kind, ()):
                raise ValueError(f"effect {effect.name!r}: scene key '{dotted}' has kind/rule "
                                 f"{getattr(spec, 'kind', spec)!r}/{getattr(spec, 'rule', None)!r}; allowed: "
                                 + "; ".join(f"{k}: {', '.join(sorted(r))}" for k, r in _KEY_RULES.items()))
            mine.add(dotted)
    for dotted in effect.plausible:
        if dotted not in mine:
            raise ValueError(f"effect {effect.name!r}: a plausible range for '{dotted}', a key it does not own")


def unregister_effect(name: str) -> Effect | None:
    """Remove an effect added by `register_effect` or a plugin (built-in effects cannot be
    removed); for a plugin that failed to load, forget the failure (returns None), so that
    the next scan tries it again."""
    if name in _BUILTIN:
        raise ValueError(f"effect {name!r} is built in and cannot be unregistered")
    _ORIGINS.pop(name, None)
    if name not in EFFECTS and name in _PLUGIN_ERRORS:
        del _PLUGIN_ERRORS[name]
        return None
    dependants = [e.name for e in EFFECTS.values() if name in e.needs]
    if dependants:
        raise ValueError(f"effect {name!r} is needed by {', '.join(dependants)}")
    return EFFECTS.pop(name)


def body_inertia(body: dict) -> np.ndarray:
    """J_c of a validated ``[body]`` table: from `box` (a homogeneous box), from `inertia`, or 0."""
    if body.get("box") is not None:
        a, bb, c = body["box"]
        m = body["mass"]
        return np.diag([m / 12 * (bb * bb + c * c), m / 12 * (a * a + c * c), m / 12 * (a * a + bb * bb)])
    if body.get("inertia") is not None:
        return np.array(body["inertia"])
    return np.zeros((3, 3))


def effect_keys() -> dict[str, dict[str, Key]]:
    """{section: {key: Key}} of every registered effect's keys ("" = top level), registry order."""
    out: dict[str, dict[str, Key]] = {}
    for e in EFFECTS.values():
        for section, sec in e.keys.items():
            out.setdefault(section, {}).update(sec)
    return out


for _e in (Gravity(), Elasticity(), RigidBody(), Reel(), Carnot(), ReelControl(), Slack(), AxialDamping(), Buoyancy(),
           Drag()):
    EFFECTS[_e.name] = _e
_BUILTIN = frozenset(EFFECTS)


# --------------------------------------------------------------------------------------------
# Plugins (entry-point group `reelbench.effects`)
# --------------------------------------------------------------------------------------------

_PLUGIN_ERRORS: dict[str, str] = {}
#: the distribution of each effect loaded through an entry point
_ORIGINS: dict = {}
_scanned = False


def load_plugins(refresh: bool = False) -> None:
    """Register the effects installed packages declare in `ENTRY_POINT_GROUP`.

    Scanned once per process (the first scene validated does it, so the benchmark's spawned
    workers do too); ``refresh`` scans again for entry points not seen yet. A plugin that
    fails to load or to register is recorded in `plugin_errors()`, not raised: the others
    still load, and a scene that lists it is refused with the reason. Plugins register in
    the order of their names, one that needs another's effect after it.
    """
    global _scanned
    if _scanned and not refresh:
        return
    _scanned = True
    pending = {}
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: ep.name):
        if ep.name in EFFECTS or ep.name in _PLUGIN_ERRORS or ep.name in pending:
            continue
        try:
            pending[ep.name] = _effect_from(ep)
            found = origin_of_distribution(getattr(ep, "dist", None))
            if found is not None:
                _ORIGINS[ep.name] = found
        except Exception as exc:  # a broken plugin must not take the others down
            _PLUGIN_ERRORS[ep.name] = f"{type(exc).__name__}: {exc}"
    while pending:
        ready = [n for n, e in pending.items() if all(need in EFFECTS for need in e.needs)] or list(pending)[:1]
        for name in ready:
            try:
                register_effect(pending.pop(name))
            except Exception as exc:
                _PLUGIN_ERRORS[name] = f"{type(exc).__name__}: {exc}"


def _effect_from(ep) -> Effect:
    obj = ep.load()
    effect = obj() if isinstance(obj, type) and issubclass(obj, Effect) else obj
    if not isinstance(effect, Effect):
        raise TypeError(f"entry point {ep.name!r} = {ep.value!r} is not an Effect subclass or instance")
    if effect.name != ep.name:
        raise ValueError(f"entry point {ep.name!r} loads an effect named {effect.name!r}")
    return effect


def ensure_known(names) -> None:
    """Load the plugins (once); scan again if ``names`` holds an effect still unknown."""
    load_plugins()
    if any(isinstance(n, str) and n not in EFFECTS and n not in _PLUGIN_ERRORS for n in names):
        load_plugins(refresh=True)


def effect_origin(name: str):
    """Where the registered effect ``name`` comes from (`models.origin.Origin`): built in, or
    a plugin's package and version (an entry point's distribution, or the module that
    registered it)."""
    effect = get_effect(name)
    if name in _BUILTIN:
        return project_origin()
    return _ORIGINS.get(name) or origin_of_object(effect)


def plugin_errors() -> dict[str, str]:
    """Effect entry points that failed to load or register, with the reason."""
    load_plugins()
    return dict(_PLUGIN_ERRORS)


def unusable() -> dict[str, str]:
    """{effect name: why a scene may not list it}: failed plugins, and registry entries added
    without `register_effect` that override `Effect.kinetic`."""
    out = {name: f"the plugin failed to load ({err})" for name, err in _PLUGIN_ERRORS.items()}
    out.update({name: _KINETIC_REFUSED for name, e in EFFECTS.items()
                if name not in _BUILTIN and _overrides_kinetic(e)})
    return out


def get_effect(name: str) -> Effect:
    """The registered effect ``name``; plugins are loaded first (e.g. in a fresh worker)."""
    if name not in EFFECTS:
        ensure_known([name])
    if name not in EFFECTS:
        reason = f": {_PLUGIN_ERRORS[name]}" if name in _PLUGIN_ERRORS else ""
        raise ValueError(f"unknown effect {name!r}{reason}; registered: {', '.join(EFFECTS)}")
    return EFFECTS[name]
