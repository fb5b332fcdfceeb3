"""The committed orders table (results/orders.csv, `python -m benchmark orders`) gives every
fixed-step method the order it declares for each situation within ±0.3 (lgvi 2 at fixed
length, 1 while reeling; lgvi_sym and rattle 2; lie_rk4, Yoshida, Suzuki 4; CG3 3; the
constant-step baselines their tableau's), measured where orders are defined: a short horizon,
at least 4 halvings, errors at least 100× the reference's own, the slope of the last halving.

Default run: the committed table is checked against theory and against its own error ladder,
and one ladder (lgvi on fixed_length) is recomputed; `-m slow`: the whole table is recomputed.
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from reelbench.benchmark.studies import orders

RESULTS = Path(__file__).resolve().parent.parent / "results"


@pytest.fixture(scope="module")
def committed():
    return pd.read_csv(RESULTS / "orders.csv"), pd.read_csv(RESULTS / "orders_errors.csv")


def _check_against_theory(summary: pd.DataFrame, ladder: pd.DataFrame, methods):
    from reelbench.integrators import get_integrator

    for scene in orders.SCENES:
        declared = {m: get_integrator(m).order_for(orders.load(scene)) for m in methods}
        rows = summary[summary.scene == scene].set_index("integrator")
        assert set(methods) <= set(rows.index), (scene, set(methods) - set(rows.index))
        for m in methods:
            r = rows.loc[m]
            assert r.declared_order == declared[m], (scene, m)
            assert abs(r.observed_order - declared[m]) <= orders.THEORY_TOLERANCE, (scene, m, r.observed_order)
            assert r.within_theory and r.halvings_run >= 4, (scene, m)
            assert r.finest_error_counted >= orders.FLOOR_FACTOR * r.reference_error, (scene, m)
    # the reference agrees with an independent eighth-order method far below every counted error
    assert (summary["reference_check"] < 1e-11).all() and (summary["reference_error"] < 1e-12).all()
    # lgvi's first order while reeling is in the table, not a tolerance
    assert set(summary.loc[(summary.integrator == "lgvi") & (summary.situation == "reel"), "declared_order"]) <= {1}


def test_the_committed_orders_match_theory(committed):
    summary, ladder = committed
    _check_against_theory(summary, ladder, orders.fixed_step_methods())


def test_the_committed_orders_follow_from_their_errors(committed):
    summary, ladder = committed
    again = orders.summarise(ladder)
    cols = ["scene", "integrator", "declared_order", "halvings_counted", "asymptotic", "within_theory"]
    pd.testing.assert_frame_equal(again[cols].reset_index(drop=True), summary[cols].reset_index(drop=True),
                                  check_dtype=False)
    assert np.allclose(again["observed_order"], summary["observed_order"], equal_nan=True)


def test_one_ladder_recomputed_matches_the_committed_one(committed):
    _, ladder = committed
    ref = orders.reference("fixed_length")
    row = orders.run_job(orders.Job("fixed_length", "lgvi", ref))
    new = pd.DataFrame(row["ladder"])
    old = ladder[(ladder.scene == "fixed_length") & (ladder.integrator == "lgvi")]
    assert np.allclose(new["dt"], old["dt"]) and np.allclose(new["error"], old["error"], rtol=0.05)
    summary = orders.summarise(new).iloc[0]
    assert abs(summary.observed_order - 2) <= orders.THEORY_TOLERANCE and summary.asymptotic


def test_the_slope_is_the_last_halving_above_the_floor():
    dts = orders.steps(2)
    errors = [1e-1, 3e-2, 4e-3, 1e-3, 2.5e-4, 1e-13]  # coarse: not yet h^2; finest: below the floor
    ladder = pd.DataFrame({"scene": "s", "integrator": "m", "situation": "fixed_length", "declared_order": 2,
                           "elements": 2, "t_end": 1.0, "dt": dts, "setting": [f"dt={h:g}" for h in dts],
                           "status": "ok", "error": errors, "reference_error": 1e-14, "reference_check": 1e-14})
    r = orders.summarise(ladder).iloc[0]
    assert r.observed_order == pytest.approx(2.0) and r.previous_slope == pytest.approx(2.0)
    assert r.halvings_counted == 4 and r.asymptotic and "below the floor at dt = 0.0025" in r.note
    ladder.loc[3, "error"] = 2e-3  # the last two slopes now disagree: flagged
    r = orders.summarise(ladder).iloc[0]
    assert not r.asymptotic and "not asymptotic" in r.note


@pytest.mark.slow
def test_the_whole_table_recomputed_matches_theory(tmp_path):
    from reelbench.benchmark.core import study

    the_study = orders.study(workers=0, echo=lambda m: None)
    assert study.run(the_study, tmp_path, command="python -m benchmark orders", log=lambda m: None) == 0
    _check_against_theory(pd.read_csv(tmp_path / "orders.csv"), pd.read_csv(tmp_path / "orders_errors.csv"),
                          orders.fixed_step_methods())


def test_a_method_without_a_constant_step_is_refused_before_any_work(tmp_path, capsys):
    from reelbench.benchmark.cli.main import main

    assert main(["orders", "--integrators", "rk45", "--out", str(tmp_path / "o")]) == 2
    assert "error: --integrators: 'rk45' has no constant-step mode" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
