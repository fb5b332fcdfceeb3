"""The energy study's modified-energy analysis (benchmark/studies/energy_drift.py): the derived offset of a
symplectic method's energy error, checked where the modified energy is known in closed form, and
the drift verdict on what is left, which tells numerical drift from a growing offset."""

import numpy as np
import pandas as pd
import pytest

from reelbench.benchmark.studies.properties import (classify, correction_of, drift_fit, energy_table, shadow_coefficient,
                                  window_means)

# --- the elastic pendulum (a point mass on a linear spring under gravity, in a plane), integrated by
# velocity Verlet: the leading term of its modified energy is known in closed form,
# H̃ = H + h² H2 with H2 = U''(v, v)/12 − |∇U|²/(24 m) (Hairer, Lubich & Wanner, Geometric Numerical
# Integration, IX.4), and the spring's axial rate gives the study's P = k (ê·v)² (m = 1)
G, K = 9.81, 100.0
R0 = G / 25 - G / K  # the spring 2:1 with the swing (ω_s = 10, ω_p = 5 rad/s): energy moves between them


def _grad(q):
    r = np.linalg.norm(q)
    return K * (r - R0) * q / r - np.array([0.0, G])


def _H2(q, v):
    r = np.linalg.norm(q)
    e = q / r
    a = e @ v
    uvv = K * a * a + K * (r - R0) / r * (v @ v - a * a)
    g = _grad(q)
    return uvv / 12 - g @ g / 24


def _verlet(h, t_end=100.0):
    """(t, E, H2, P) along a velocity-Verlet run of the elastic pendulum."""
    q, v = np.array([np.sin(0.5), np.cos(0.5)]) * (R0 + G / K) * 1.01, np.zeros(2)
    n = int(round(t_end / h))
    out = np.empty((n + 1, 4))
    a = -_grad(q)
    for i in range(n + 1):
        r = np.linalg.norm(q)
        out[i] = (i * h, 0.5 * v @ v + 0.5 * K * (r - R0) ** 2 - G * q[1], _H2(q, v), K * (q / r @ v) ** 2)
        v = v + 0.5 * h * a
        q = q + h * v
        a = -_grad(q)
        v = v + 0.5 * h * a
    return out.T


def test_the_closed_form_modified_energy_takes_out_the_error_to_the_next_order():
    left = {}
    for h in (0.02, 0.01):
        t, E, H2, _ = _verlet(h)
        dE = E - E[0]
        left[h] = np.abs(dE + h * h * (H2 - H2[0])).max()
        assert left[h] < np.abs(dE).max() / 50  # (hω_s)² = 0.04 and 0.01: the h² term is all but all of it
    assert 12 < left[0.02] / left[0.01] < 20  # what is left is O(h⁴)


def test_the_mode_averaged_offset_is_the_closed_form_one_averaged():
    # averaged over a harmonic mode, ⟨H2⟩ = c_2 ω² E_m = c_2 ⟨P⟩: the closed-form H2 of a
    # harmonic oscillator (ω = 3) along its Verlet orbit against shadow_coefficient's 1/24
    w, h = 3.0, 1e-3
    q, p = 1.0, 0.0
    vals = []
    for _ in range(int(2 * np.pi / w / h) * 20):
        vals.append((w * w * p * p / 12 - w ** 4 * q * q / 24, 0.5 * (p * p + w * w * q * q)))
        p -= 0.5 * h * w * w * q
        q += h * p
        p -= 0.5 * h * w * w * q
    H2, E = np.array(vals).T
    assert H2.mean() / (w * w * E.mean()) == pytest.approx(shadow_coefficient(), rel=2e-3)
    assert shadow_coefficient() == pytest.approx(1 / 24, rel=1e-3)


def test_the_composition_coefficients_follow_from_their_substeps():
    from reelbench.integrators.lgvi_sym import SUZUKI4, YOSHIDA4

    assert shadow_coefficient(YOSHIDA4, 4) == pytest.approx(-0.06614, rel=1e-3)
    assert shadow_coefficient(SUZUKI4, 4) == pytest.approx(-0.000930, rel=1e-2)
    assert abs(shadow_coefficient(YOSHIDA4, 2)) < 1e-3  # no h² term: fourth order
    order, c, h = correction_of("lgvi_suzuki4", "dt=0.005")
    assert (order, h) == (4, 0.005) and c == pytest.approx(shadow_coefficient(SUZUKI4, 4))
    assert correction_of("lgvi", "dt=0.0025")[:2] == (2, pytest.approx(1 / 24, rel=1e-3))
    assert correction_of("dopri8", "rtol=1e-08, atol=1e-10") is None and correction_of("lie_rk4", "dt=0.005") is None


def test_the_averaged_offset_cuts_the_window_mean_error_of_the_verlet_pendulum():
    # the study's correction, −(h²/24)⟨P⟩ over windows, on the pendulum whose swing feeds the
    # spring: it takes out a large part of the window means' change, and a fit finds a coefficient
    # of the derived sign and size (the spring is only twice as fast as the swing here)
    h = 0.01
    t, E, _, P = _verlet(h, 200.0)
    tc, d, p = window_means(t, E - E[0], P, width=2.0)
    assert np.ptp(p) / p.min() > 1.0  # the axial energy changes
    assert np.ptp(d + h * h / 24 * p) < np.ptp(d) / 2
    fit = drift_fit(t, E - E[0], h * h * P, width=2.0)
    assert -1.5 / 24 < fit["a"] < -0.5 / 24 and fit["drift_verdict"] == "bounded"


T = np.arange(0.0, 1000.0 + 1e-9, 0.1)


def _offset(rng):
    """A growing state regressor like h²⟨P⟩: irregular growth with a fast oscillation on top."""
    slow = np.cumsum(rng.standard_normal(T.size)) / np.sqrt(T.size)
    return 1e-2 * (0.2 + (T / T[-1]) ** 1.5 + 0.3 * np.abs(slow)) * (1 + 0.5 * np.sin(37.0 * T))


def test_a_linear_drift_under_a_growing_offset_is_drifting(rng):
    x = _offset(rng)
    err = -(1 / 24) * x + 2e-4 * T / T[-1] + 2e-5 * rng.standard_normal(T.size)
    fit = drift_fit(T, err, x)
    assert fit["drift_verdict"] == "drifting" and fit["drift"] == pytest.approx(2e-4, rel=0.1)
    assert fit["a"] == pytest.approx(-1 / 24, rel=0.05)


def test_a_growing_offset_alone_is_bounded_where_the_slope_test_sees_growth(rng):
    x = _offset(rng)
    err = -(1 / 24) * x + 2e-5 * rng.standard_normal(T.size)
    fit = drift_fit(T, err, x)
    assert fit["drift_verdict"] == "bounded" and abs(fit["drift"]) < fit["scatter"]
    assert classify(T, np.abs(err))["verdict"] != "bounded"  # the raw slope test takes the offset for growth


def test_the_study_table_takes_its_verdict_after_the_correction(rng):
    x = _offset(rng) / 0.005 ** 2  # ⟨P⟩/max T, 1/s²
    offset = -(1 / 24) * 0.005 ** 2 * x
    rows = []
    for name, dev in (("lgvi", offset), ("lie_rk4", offset + 1e-4 * T / T[-1])):
        dev = dev + 1e-6 * rng.standard_normal(T.size)
        rows.append(pd.DataFrame({"t": T, "energy_error": np.abs(dev), "energy_dev": dev, "axial_P": x,
                                  "axial_P4": x * 1e4, "tension_min": -1.0, "method": f"{name} dt=0.005 N=10",
                                  "integrator": name, "scene": "fixed_length", "elements": 10, "setting": "dt=0.005",
                                  "status": "ok"}))
    table = energy_table(pd.concat(rows, ignore_index=True)).set_index("integrator")
    assert table.loc["lgvi", "verdict"] == "bounded" and table.loc["lgvi", "raw_verdict"] != "bounded"
    assert table.loc["lgvi", "c"] == pytest.approx(-1 / 24, rel=1e-3)
    assert table.loc["lgvi", "corrected_max"] < table.loc["lgvi", "mean_error_max"] / 20
    assert table.loc["lie_rk4", "verdict"] == "drifting" and table.loc["lie_rk4", "correction"] == "none"
