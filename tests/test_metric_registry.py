"""One metric registry: runs.csv, `check` and the stability map read `metrics.METRICS`."""

import numpy as np
import pandas as pd

from reelbench.benchmark.studies import check
from reelbench.benchmark.runs import metrics
from reelbench.integrators import get_integrator
from reelbench.models import build_model, load_scene
from reelbench.models.diagnostics import evaluate, summary


def test_every_reader_lists_every_registry_metric():
    """The readers' tables (runs.csv's `metrics.COLUMNS`, the drift baseline's `check.COLUMNS`,
    the stability map's `stability.COLUMNS`) hold every metric in registry order, the map no
    reference metric, and `check` compares each metric with the registry's floor: a reader that
    stops taking its metrics from `METRICS` fails here. (That `ACCURACY`, `CONSERVATION`,
    `FLOORS` and `DIRECTIONS` are the registry's holds by their definitions: not asserted.)"""
    from reelbench.benchmark.studies import stability

    names = [m.name for m in metrics.METRICS]
    assert len(set(names)) == len(names)
    assert [c for c in metrics.COLUMNS if c in names] == names  # runs.csv columns, in registry order
    assert [c for c in check.COLUMNS if c in names] == names  # the drift baseline's columns
    assert not {m.name for m in metrics.METRICS if m.reference} & set(stability.COLUMNS)  # the map has no reference
    assert set(metrics.DIRECTIONS.values()) <= {"lower", "higher"}
    assert all(m.description and m.floor > 0 for m in metrics.METRICS)
    # check reads each metric's floor: x1000 worse but under the floor passes, above it fails
    for m in metrics.METRICS:
        row = {"scene": "s", "integrator": "i", "setting": "dt=0.01", "status": "ok", **{n: 0.0 for n in names}}
        base = pd.DataFrame([{**row, m.name: m.floor / 1e4}]).reindex(columns=check.COLUMNS)
        under = pd.DataFrame([{**row, m.name: m.floor / 10}]).reindex(columns=check.COLUMNS)
        over = pd.DataFrame([{**row, m.name: m.floor * 10}]).reindex(columns=check.COLUMNS)
        assert not check.compare(base, under, registered=["i"]).failed, m.name
        assert {r["metric"] for r in check.compare(base, over, registered=["i"]).regressions} == {m.name}


def test_stability_map_table_holds_every_conservation_metric():
    """metrics.Metric: the stability map reports the metrics that need no reference."""
    from reelbench.benchmark.studies import stability

    conservation = [m.name for m in metrics.METRICS if not m.reference]
    assert conservation and set(conservation) <= set(stability.COLUMNS)


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
