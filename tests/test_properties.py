"""The generated "which property pays off where" section (benchmark/properties.py): the drift
ratio tells a bounded oscillating error from a drifting one, and the words follow the numbers."""

import numpy as np
import pandas as pd

from benchmark.properties import BOUNDED_BELOW, DRIFTING_ABOVE, drift_ratio, properties_text


def test_drift_ratio_separates_oscillation_from_drift(rng):
    t = np.linspace(0.0, 100.0, 1001)
    bounded = 1e-3 * (1.0 + np.sin(2.0 * np.pi * t / 7.3)) + 1e-4 * rng.random(t.size)
    drifting = 1e-6 * t + 1e-5 * rng.random(t.size)
    assert drift_ratio(t, bounded) < BOUNDED_BELOW
    assert drift_ratio(t, drifting) > DRIFTING_ABOVE
    assert np.isnan(drift_ratio(t[:3], drifting[:3]))


def _study(rng):
    t = np.linspace(0.0, 100.0, 501)
    rows = [pd.DataFrame({"t": t, "energy_error": 1e-3 * (1 + np.sin(t)) + 1e-5 * rng.random(t.size),
                          "method": "lgvi dt=0.005", "integrator": "lgvi"}),
            pd.DataFrame({"t": t, "energy_error": 1e-7 * t + 1e-7 * rng.random(t.size),
                          "method": "lie_rk4 dt=0.005", "integrator": "lie_rk4"})]
    return pd.concat(rows, ignore_index=True)


def test_the_words_follow_the_numbers(tmp_path, rng):
    runs = pd.DataFrame({"integrator": ["lgvi", "lie_rk4", "rk45", "rk45"], "status": ["ok", "ok", "ok", "diverged"],
                         "orthogonality_error": [3e-14, 2e-14, 5e-7, 1.0]})
    path = tmp_path / "energy_horizon.csv"
    _study(rng).to_csv(path, index=False)
    text = properties_text(runs, path)
    assert "Symplecticity pays off over a long horizon" in text
    assert "Bounded is not small: at the study's settings `lie_rk4`" in text
    assert "Staying on the group pays off in orthogonality" in text and "`rk45` 5.0e-07" in text
    # a symplectic method that drifts turns the verdict, and so does a group method off the group
    study = _study(rng)
    study.loc[study.method.str.startswith("lgvi"), "energy_error"] = 1e-6 * study.t
    study.to_csv(path, index=False)
    runs.loc[0, "orthogonality_error"] = 1e-6
    text = properties_text(runs, path)
    assert "Symplecticity is not visible at this horizon" in text
    assert "shows no difference here" in text and "(not: `lgvi`)" in text
    assert "No energy study" in properties_text(runs, tmp_path / "missing.csv")
