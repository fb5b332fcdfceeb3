"""Hard cases: the hard scenes, the divergence guards, and every run either stays
bounded or stops with a named status, keeping only finite results.

Fast tests use small N or short horizons where the point survives (each model compiles once,
a few seconds); the whole matrix of hard scene × integrator at the stability map's settings is
marked ``slow``. The outcomes asserted here are the ones `results/stability/README.md` reports.
"""

import numpy as np
import pytest

from reelbench.integrators import Status, get_integrator
from reelbench.integrators import lgvi as lgvi_module
from reelbench.integrators.base import energy_bound, energy_scale
from reelbench.models import available_scenes, build_model, load_scene
from reelbench.models.diagnostics import evaluate, summary

HARD = ("stiff_string", "many_elements", "fast_spin", "retrieval_to_limit", "deployment_to_end", "long_horizon",
        "near_slack", "strong_drag")
NAMED = {s.value for s in Status} - {"ok"}


def finite_diagnostics(scene, traj):
    """Every saved state and every diagnostic is finite (no NaN is ever returned)."""
    assert len(traj.t) >= 1
    for a in (traj.t, traj.x, traj.velocity, traj.work, traj.attitude):
        if a is not None:
            assert np.all(np.isfinite(a))
    df = evaluate(scene, traj)
    assert np.all(np.isfinite(df.to_numpy(dtype=float)))
    return df


def within_energy_bound(scene, df):
    model = build_model(scene)
    err = np.abs(df["energy_minus_work"] - df["energy_minus_work"].iloc[0])
    assert err.max() <= energy_bound(model)


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------
def test_hard_scenes_ship_with_their_defining_values():
    assert set(HARD) <= set(available_scenes())
    for name in HARD:
        assert load_scene(name).description.startswith("Hard case")
    assert load_scene("stiff_string").string.axial_stiffness == 100 * load_scene("fixed_length").string.axial_stiffness
    assert load_scene("stiff_string").string.elements == 40
    assert load_scene("many_elements").string.elements == 320
    assert np.linalg.norm(load_scene("fast_spin").initial.angular_velocity) == pytest.approx(30.0, rel=1e-3)
    assert load_scene("long_horizon").t_end >= 500
    assert load_scene("near_slack").initial.stretch == 0.95
    r = load_scene("retrieval_to_limit")
    assert r.has("reel_control") and r.reel.min_deployed_length > 0
    assert load_scene("deployment_to_end").t_end > 9.2  # the string runs out at t ~ 9.2 s
    assert load_scene("strong_drag").section("fluid")["current"] == [0.0, 3.0, 0.0]


def test_near_slack_start_is_compressed_by_five_percent():
    scene = load_scene("near_slack")
    model = build_model(scene)
    x, R, w = model.initial_state()
    np.testing.assert_allclose(np.asarray(model.tensions(x)), -0.05 * scene.string.axial_stiffness, rtol=1e-12)
    assert scene.with_(stretch=1.0, name="fixed_length", t_end=10.0).key() == load_scene("fixed_length").key()


def test_energy_scale_covers_what_the_scene_can_exchange():
    """The scale is at least the gravity reach of string and body and grows with what the scene
    can supply: a stronger reel moment (more work over the string) raises it by |Δu| L / d."""
    scene = load_scene("retrieval")
    model = build_model(scene)
    assert energy_scale(model) > model.g * (model.m_b + model.mu * model.L) * model.L
    stronger = build_model(scene.with_(control_moment=2 * scene.reel.control_moment))
    extra = abs(scene.reel.control_moment) * model.L / model.d
    np.testing.assert_allclose(energy_scale(stronger) - energy_scale(model), extra, rtol=1e-9)


# ------------------------------------------------------------------------------------------
# Guards
# ------------------------------------------------------------------------------------------
def test_unstable_lgvi_step_diverges_and_keeps_the_good_prefix():
    """dt = 20 ms is far beyond h·ω_max < 2 (ω_max ~ 220 rad/s at N = 10): the run stops with
    "diverged" (energy guard) and keeps only finite saved states before the blow-up."""
    scene = load_scene("fixed_length")
    tr = get_integrator("lgvi").solve(scene, t_end=2.0, dt=0.02, save_every=0.02)
    assert tr.status == Status.DIVERGED.value
    assert "energy balance error" in tr.reason and "kept up to" in tr.reason
    assert 0 < tr.t[-1] < 2.0 and len(tr.t) >= 3
    df = finite_diagnostics(scene, tr)
    within_energy_bound(scene, df)
    # the kept prefix is the same as a stable run's first steps would give at this dt: it is
    # the prefix, not a repaired state
    tr2 = get_integrator("lgvi").solve(scene, t_end=float(tr.t[-1]), dt=0.02, save_every=0.02)
    np.testing.assert_allclose(tr2.x, tr.x, rtol=0, atol=1e-12)


def test_cayley_guard_stops_a_step_that_rotates_too_far(monkeypatch):
    """With the bound lowered to |c| = 0.1 (11.4 deg per step), a 30 rad/s spin at dt = 10 ms
    (|c| ~ 0.15) trips the Cayley guard: status diverged, reason naming the Cayley parameter."""
    scene = load_scene("fast_spin", elements=2)
    ok = get_integrator("lgvi").solve(scene, t_end=0.2, dt=0.01)  # compiled with the default bound
    assert ok.ok, ok.reason
    # the bound is a run-time argument of the compiled loop: lowering it reuses the same compiled run
    monkeypatch.setattr(lgvi_module, "CAYLEY_BOUND", 0.1)
    tr = get_integrator("lgvi").solve(scene, t_end=0.2, dt=0.01)
    assert tr.stats["compile_time"] < 0.5 * ok.stats["compile_time"]
    assert tr.status == Status.DIVERGED.value and "Cayley parameter" in tr.reason
    assert tr.stats["steps"] == 0 and len(tr.t) == 1
    finite_diagnostics(scene, tr)


def test_scipy_energy_guard_on_a_useless_tolerance():
    scene = load_scene("fixed_length")
    tr = get_integrator("rk45").solve(scene, t_end=2.0, rtol=0.5, atol=10.0)
    assert tr.status == Status.DIVERGED.value and "energy balance error" in tr.reason
    within_energy_bound(scene, finite_diagnostics(scene, tr))


def test_diffrax_constant_step_blow_up_keeps_only_points_within_the_bound():
    scene = load_scene("fixed_length")
    tr = get_integrator("tsit5").solve(scene, t_end=2.0, dt=0.02, save_every=0.02)
    assert tr.status == Status.DIVERGED.value and "energy balance error" in tr.reason
    assert tr.t[-1] < 0.5
    within_energy_bound(scene, finite_diagnostics(scene, tr))


# ------------------------------------------------------------------------------------------
# Each hard scene, at settings that keep the fast suite fast
# ------------------------------------------------------------------------------------------
def test_stiff_string_lgvi_stable_below_and_named_status_above_its_limit():
    scene = load_scene("stiff_string", elements=8)  # EA stays 100x: ω_max ~ 1.7e3 rad/s, h ω_max < 2 needs h < ~1 ms
    energy = []
    for h in (1e-4, 5e-5):  # h ω_max ~ 0.17, 0.085
        ok = get_integrator("lgvi").solve(scene, t_end=0.02, dt=h)
        assert ok.ok, ok.reason
        energy.append(summary(finite_diagnostics(scene, ok), has_work=False)["energy_error"])
    # stable: the energy error is the LGVI's O(h²) one (measured 2.2e-8, 5.4e-9: ratio 4.0), not growth
    assert 3.0 < energy[0] / energy[1] < 5.0 and energy[0] < 1e-6, energy
    bad = get_integrator("lgvi").solve(scene, t_end=0.2, dt=2e-3)
    assert bad.status in NAMED and bad.reason
    finite_diagnostics(scene, bad)


def test_many_elements_lgvi_takes_its_steps_finitely_and_keeps_R_orthogonal():
    """N = 320 at h = 0.1 ms for 5 ms: every step taken, finite, R on SO(3) (stability over the
    horizon is the slow matrix's and the stability map's)."""
    scene = load_scene("many_elements")
    tr = get_integrator("lgvi").solve(scene, t_end=0.005, dt=1e-4)
    assert tr.ok, tr.reason
    for a in (tr.x, tr.velocity, tr.momentum, tr.attitude):  # (diagnostics at N = 320: the slow matrix)
        assert np.all(np.isfinite(a))
    R = tr.attitude[-1]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-13
    assert tr.stats["steps"] == round(0.005 / 1e-4)


def test_retrieval_to_limit_ends_at_its_lower_limit():
    scene = load_scene("retrieval_to_limit", deployed_length=2.4, elements=3)
    tr = get_integrator("lgvi").solve(scene, dt=1e-3)
    assert tr.status == Status.LENGTH_LIMIT.value, tr.reason
    assert "lower limit" in tr.reason
    df = finite_diagnostics(scene, tr)
    # the last step kept is the one before the limit: within one step's travel |ṡ_p| h of it
    gap = df["deployed_length"].iloc[-1] - scene.reel.min_deployed_length
    assert 0 < gap <= 2 * abs(tr.velocity[-1, 0]) * 1e-3, gap
    assert df["deployed_length"].min() > scene.reel.min_deployed_length


def test_deployment_to_end_ends_when_the_string_runs_out():
    scene = load_scene("deployment_to_end", deployed_length=37.5, elements=3)
    tr = get_integrator("rk45").solve(scene, rtol=1e-6, atol=1e-8)
    assert tr.status == Status.LENGTH_LIMIT.value, tr.reason
    assert "upper limit" in tr.reason and "ran out" in tr.reason
    df = finite_diagnostics(scene, tr)
    model = build_model(scene)
    assert tr.stats["event_time"] > tr.t[-1]
    # between the last saved point and the event the string, deploying at |ṡ_p| and accelerating
    # by less than g (the reel's inertia holds it back), covers the gap to L - b
    gap, dt_left, v = model.L - model.b - df["deployed_length"].iloc[-1], tr.stats["event_time"] - tr.t[-1], abs(tr.velocity[-1, 0])
    assert v * dt_left <= gap <= (v + model.g * dt_left) * dt_left, (gap, v, dt_left)


def test_near_slack_start_stays_bounded_with_the_lgvi():
    scene = load_scene("near_slack")
    tr = get_integrator("lgvi").solve(scene, t_end=1.0, dt=2.5e-3)
    assert tr.ok, tr.reason
    df = finite_diagnostics(scene, tr)
    assert df["tension_min"].iloc[0] == pytest.approx(-0.05 * scene.string.axial_stiffness)  # 5 % compressed
    half = get_integrator("lgvi").solve(scene, t_end=1.0, dt=1.25e-3)
    assert half.ok, half.reason
    energy = [summary(df, has_work=False)["energy_error"], summary(evaluate(scene, half), has_work=False)["energy_error"]]
    # bounded: the LGVI's O(h²) energy error (measured 3.1e-4, 7.7e-5: ratio 4.1), not growth
    assert 3.0 < energy[0] / energy[1] < 5.0 and energy[0] < 1e-3, energy


# ------------------------------------------------------------------------------------------
# The whole matrix (slow): hard scene × integrator at the stability map's settings
# ------------------------------------------------------------------------------------------
SLOW_SETTINGS = {
    "lgvi": {"dt": None},
    "rk45": {"rtol": 1e-6, "atol": 1e-8},
    "dop853": {"rtol": 1e-6, "atol": 1e-8},
    "tsit5": {"rtol": 1e-6, "atol": 1e-8},
    "radau": {"rtol": 1e-6, "atol": 1e-8},
    "kvaerno5": {"rtol": 1e-6, "atol": 1e-8},
}
#: (horizon, overrides, expected status, LGVI dt) per hard scene; shorter than the map's horizons
SLOW_CASES = {
    "stiff_string": (0.05, {}, "ok", 1.25e-4),
    "many_elements": (0.002, {}, "ok", 1.25e-4),
    "fast_spin": (0.5, {}, "ok", 5e-3),
    "retrieval_to_limit": (10.0, {"deployed_length": 3.0}, "length_limit", 1e-3),
    "deployment_to_end": (10.0, {"deployed_length": 37.0}, "length_limit", 2.5e-3),
    "long_horizon": (50.0, {}, "ok", 5e-3),
    "near_slack": (1.0, {}, "ok", 2.5e-3),
}


@pytest.mark.slow
@pytest.mark.parametrize("integrator", list(SLOW_SETTINGS))
@pytest.mark.parametrize("scene_name", list(SLOW_CASES))
def test_hard_scene_matrix(scene_name, integrator):
    horizon, ov, expected, dt = SLOW_CASES[scene_name]
    if scene_name == "many_elements" and integrator in ("radau", "kvaerno5"):
        pytest.skip("implicit baselines on N = 320: dense autodiff Jacobian of a 1,927-dim state (see the map)")
    if integrator == "kvaerno5":  # measured: the first case had not finished after 25 min on the shared 2 cores
        pytest.skip("kvaerno5 (full-Newton ESDIRK through the autodiff model) compiles and runs for minutes per scene")
    scene = load_scene(scene_name, **ov)
    kw = dict(SLOW_SETTINGS[integrator])
    if integrator == "lgvi":
        kw["dt"] = dt
    tr = get_integrator(integrator).solve(scene, t_end=horizon, **kw)
    assert tr.status == expected, tr.reason
    df = finite_diagnostics(scene, tr)
    within_energy_bound(scene, df)
    if expected == "ok":  # the LGVI's bounded oscillation reaches ~1.4e-2 of max T at dt = 5 ms (see the map)
        assert summary(df, has_work=build_model(scene).layout.has_work)["energy_error"] < 5e-2
