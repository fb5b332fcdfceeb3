"""One metric registry (issue #14): runs.csv, `check` and the stability map read `metrics.METRICS`."""

import numpy as np

from benchmark import check, metrics
from integrators import get_integrator
from models import build_model, load_scene
from models.diagnostics import evaluate, summary


def test_every_reader_takes_its_metrics_from_the_registry():
    names = [m.name for m in metrics.METRICS]
    assert metrics.ACCURACY == names
    assert [c for c in metrics.COLUMNS if c in names] == names  # runs.csv columns, in registry order
    assert check.FLOORS == {m.name: m.floor for m in metrics.METRICS}
    assert set(metrics.DIRECTIONS.values()) <= {"lower", "higher"}
    assert metrics.CONSERVATION == [m.name for m in metrics.METRICS if not m.reference]
    assert all(m.description for m in metrics.METRICS)


def test_registry_conservation_metrics_equal_the_diagnostics_summary():
    """models.diagnostics.summary (the paper's metrics, used by `simulate`) and the registry
    compute the same three numbers: pinned together, bit for bit."""
    scene = load_scene("fixed_length", elements=2)
    traj = get_integrator("lgvi").solve(scene, t_end=0.2, dt=0.005, save_every=0.02)
    ref = get_integrator("lgvi").solve(scene, t_end=0.2, dt=0.0025, save_every=0.02)
    got = metrics.run_metrics(scene, traj, ref, 0.02)
    assert list(got) == metrics.ACCURACY
    want = summary(evaluate(scene, traj), has_work=build_model(scene).layout.has_work)
    assert {k: got[k] for k in want} == want
    assert 0 < got["position_error_max"] and got["position_error_final"] <= got["position_error_max"]
    # no reference: the reference metrics are NaN, the others unchanged
    alone = metrics.run_metrics(scene, traj, None, 0.02)
    assert all(np.isnan(alone[m.name]) for m in metrics.METRICS if m.reference)
    assert {k: alone[k] for k in want} == want
