"""The generated "which property pays off where" section (benchmark/studies/properties.py; the verdicts, benchmark/studies/energy_drift.py): the raw slope
classifier tells a bounded error from a drifting one (and says when it cannot; it decides for a
table without the signed error, see tests/test_modified_energy.py for the verdict after the
modified-energy offset), and the words follow the numbers."""

import numpy as np
import pandas as pd

from reelbench.benchmark.studies.properties import BOUNDED_BELOW, DRIFTING_FROM, classify, energy_table, properties_text

T = np.linspace(0.0, 100.0, 1001)


def test_a_linear_drift_is_drifting(rng):
    c = classify(T, 1e-6 * T + 1e-6 * rng.random(T.size))
    assert c["verdict"] == "drifting" and abs(c["slope"] - 1.0) < 0.1 and c["growth"] > 5


def test_a_bounded_oscillation_is_bounded(rng):
    err = 1e-3 * (1.0 + np.sin(2.0 * np.pi * T / 1.3)) * (0.7 + 0.3 * rng.random(T.size))
    c = classify(T, err)
    assert c["verdict"] == "bounded" and abs(c["slope"]) < BOUNDED_BELOW and c["slope_high"] < DRIFTING_FROM


def test_a_band_that_fills_up_and_then_stays_is_bounded(rng):
    # the error rises for 40 s (the motion explores its states), then stays in its band
    err = 1e-4 * np.minimum(1.0, 0.1 + T / 40.0) * (1.0 + np.sin(2.0 * np.pi * T / 1.3)) * (0.8 + 0.2 * rng.random(T.size))
    c = classify(T, err)
    assert c["verdict"] == "bounded" and c["slope_all"] > 0.3  # over the whole horizon it would look like growth


def test_what_it_cannot_decide_is_undecided_with_its_figures(rng):
    slow = classify(T, 1e-4 * np.maximum(T, 1e-3) ** 0.35)  # a slow growth, between the two
    assert slow["verdict"] == "undecided" and 0.3 < slow["slope"] < 0.4
    scattered = classify(T, 1e-4 * np.exp(2.5 * rng.standard_normal(T.size)) * (1 + T / 100))
    assert scattered["verdict"] == "undecided" or scattered["slope_high"] - scattered["slope_low"] < 0.5
    short = classify(T[:3], T[:3])
    assert short["verdict"] == "undecided" and np.isnan(short["slope"])


def _study(rng, lgvi=None):
    t = np.linspace(0.0, 100.0, 501)
    rows = []
    for n in (4, 10):
        for dt in (0.005, 0.0025):
            band = 1e-3 * (dt / 0.005) ** 2 * (1 + np.sin(5 * t)) * (0.8 + 0.2 * rng.random(t.size))
            rows.append(pd.DataFrame({"t": t, "energy_error": band if lgvi is None else lgvi(t),
                                      "tension_min": -1.0, "method": f"lgvi dt={dt:g} N={n}", "integrator": "lgvi",
                                      "scene": "fixed_length", "elements": n, "setting": f"dt={dt:g}", "status": "ok"}))
            rows.append(pd.DataFrame({"t": t, "energy_error": 1e-7 * t + 1e-8 * rng.random(t.size),
                                      "tension_min": -1.0, "method": f"lie_rk4 dt={dt:g} N={n}",
                                      "integrator": "lie_rk4", "scene": "fixed_length", "elements": n,
                                      "setting": f"dt={dt:g}", "status": "ok"}))
    return pd.concat(rows, ignore_index=True)


def test_every_run_of_the_study_is_classified(rng):
    table = energy_table(_study(rng))
    assert len(table) == 8 and set(table["elements"]) == {4, 10}
    assert set(table.loc[table.integrator == "lgvi", "verdict"]) == {"bounded"}
    assert set(table.loc[table.integrator == "lie_rk4", "verdict"]) == {"drifting"}


def test_the_words_follow_the_numbers(tmp_path, rng):
    runs = pd.DataFrame({"integrator": ["lgvi", "lie_rk4", "rk45", "rk45"], "status": ["ok", "ok", "ok", "diverged"],
                         "orthogonality_error": [3e-14, 2e-14, 5e-7, 1.0]})
    path = tmp_path / "energy_horizon.csv"
    _study(rng).to_csv(path, index=False)
    text = properties_text(runs, path)
    assert "Symplecticity pays off over a long horizon" in text
    assert "`lgvi` N=10 dt=0.005 on fixed_length: bounded (slope" in text
    assert "`lie_rk4` N=4 dt=0.0025 on fixed_length: drifting (slope 1.0" in text
    assert "Staying on the group pays off in orthogonality" in text and "`rk45` 5.0e-07" in text
    # a symplectic method that drifts turns the verdict, naming the runs, and so does a group method off the group
    _study(rng, lgvi=lambda t: 1e-6 * t).to_csv(path, index=False)
    runs.loc[0, "orthogonality_error"] = 1e-6
    text = properties_text(runs, path)
    assert "Symplecticity is not shown everywhere" in text and "`lgvi` at N=10 dt=0.005 on fixed_length is drifting" in text
    assert "shows no difference here" in text and "(not: `lgvi`)" in text
    assert "No energy study" in properties_text(runs, tmp_path / "missing.csv")
