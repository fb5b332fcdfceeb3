"""reelbench.benchmark.runs.reproducibility: what two runs tables from different CPUs must share, checked on
the measured pair (tests/data) and on small made-up differences."""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from reelbench.benchmark.runs.ranking import failure_causes, failure_summary
from reelbench.benchmark.runs.reproducibility import DEFAULT_TOLERANCE, AgreementTolerance, compare_runs, reproducible, statement

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def measured():
    return pd.read_csv(DATA / "runs_committed.csv"), pd.read_csv(DATA / "runs_epyc.csv")


def test_the_measured_cross_cpu_differences_are_within_the_default_tolerance(measured):
    c = compare_runs(*measured)
    assert reproducible(c)
    assert c["verdict"].value_counts().to_dict() == {"within tolerance": 128, "equal": 18, "stopped elsewhere": 1}
    stopped = c[c["verdict"] == "stopped elsewhere"].iloc[0]
    assert (stopped["integrator"], stopped["setting"], stopped["steps_a"], stopped["steps_b"]) == ("tsit5", "dt=0.01", 689, 526)
    text = statement(c)
    assert text.startswith("147 runs compared: 18 equal to the last digit, 128 within tolerance")
    assert "1 stopped elsewhere: `tsit5` dt=0.01 on fixed_length (both diverged, after 689 vs 526 steps)" in text
    assert text.endswith("every other claim holds.")


@pytest.mark.parametrize("tighter, breaks", [
    ({"adaptive_steps_rtol": 0.01}, "steps 475 vs 481"),  # dop853 on deployment: 1.25 % more steps
    ({"adaptive_error_factor": 1.5}, "attitude_error_final 0.00053 vs 0.000342"),  # radau rtol 1e-3
    ({"adaptive_error_of_rtol": 0.0}, "pi3_error 1.01e-07 vs 2.7e-06"),  # dop853 rtol 1e-4: a factor 27
])
def test_each_default_tolerance_is_needed_by_the_measured_differences(measured, tighter, breaks):
    c = compare_runs(*measured, tol=AgreementTolerance(**{**DEFAULT_TOLERANCE.__dict__, **tighter}))
    assert not reproducible(c)
    assert any(breaks in r for r in c.loc[c["verdict"] == "differs", "reason"])


@pytest.fixture(scope="module")
def rattle_measured():
    """RATTLE's default-sweep rows as committed, and the same runs on an Emerald Rapids Xeon
    (AVX-512, a fresh clone's `run --fresh`) and on that Xeon with XLA held to AVX2
    (fixed_length only): its finest steps differ on each CPU (tests/data/README.md)."""
    committed = pd.read_csv(DATA / "rattle_committed.csv")
    others = {name: pd.read_csv(DATA / f"rattle_xeon_{name}.csv") for name in ("avx512", "avx2")}
    keys = ["scene", "integrator", "setting"]
    return {name: (committed[committed.set_index(keys).index.isin(b.set_index(keys).index)], b)
            for name, b in others.items()}


def test_rattle_across_cpus_is_within_the_default_tolerance(rattle_measured):
    """Every status and step count equal, the finest steps' errors apart by round-off that the
    dynamics amplify: within the default tolerance, with a margin of 4 or more."""
    for name, (a, b) in rattle_measured.items():
        c = compare_runs(a, b)
        assert reproducible(c), (name, c[c["verdict"] == "differs"])
        assert (a["steps"].values == b["steps"].values).all() and (a["status"].values == b["status"].values).all()
        assert (c["verdict"] == "within tolerance").sum() >= 7 and c["used"].max() < 0.25, name


@pytest.mark.parametrize("cpu, tighter, breaks", [
    ("avx2", {"fixed_error_rtol": 1e-3}, "attitude_error_max 4.44e-05 vs 4.43e-05"),  # 1.2e-3 relative
    ("avx2", {"fixed_error_atol": 0.0}, "pi3_error 6.19e-10 vs 8.81e-10"),  # 2.6e-10 near the floor
    ("avx512", {"fixed_error_rtol": 1e-6, "fixed_error_atol": 0.0}, "attitude_error_final 1.25e-05 vs 1.25e-05"),
])
def test_each_fixed_step_tolerance_is_needed_by_rattles_differences(rattle_measured, cpu, tighter, breaks):
    c = compare_runs(*rattle_measured[cpu], tol=AgreementTolerance(**{**DEFAULT_TOLERANCE.__dict__, **tighter}))
    assert not reproducible(c)
    assert any(breaks in r for r in c.loc[c["verdict"] == "differs", "reason"])


def test_the_failures_and_their_causes_are_the_same_on_both_machines(measured):
    # every run that did not finish on one CPU failed at the same setting, for the same reason, on the other
    key = ["scene", "integrator", "setting", "status", "cause"]
    a, b = (failure_causes(t)[key].sort_values(key).reset_index(drop=True) for t in measured)
    assert len(a) == 19
    pd.testing.assert_frame_equal(a, b)
    assert failure_summary(measured[0]) == failure_summary(measured[1])
    assert failure_summary(measured[0]).startswith("19 of 147 runs not ok, all expected")


def run(integrator="m", setting="dt=0.01", status="ok", steps=100, **errors):
    axis, value = setting.split("=")
    return {"scene": "s", "integrator": integrator, "setting": setting, "dt": float(value) if axis == "dt" else np.nan,
            "rtol": float(value) if axis == "rtol" else np.nan, "status": status, "steps": steps,
            "energy_error": errors.get("energy_error", 1e-5 if status == "ok" else np.nan)}


def verdict(a, b, tol=DEFAULT_TOLERANCE):
    c = compare_runs(pd.DataFrame(a), pd.DataFrame(b), tol)
    return c.set_index(["integrator", "setting"])["verdict"].to_dict()


def test_a_status_may_change_only_at_the_stability_limit():
    ladder = [run(setting="dt=0.02", status="diverged"), run(setting="dt=0.01"), run(setting="dt=0.005")]
    flipped_limit = [ladder[0], run(setting="dt=0.01", status="diverged"), ladder[2]]
    assert verdict(ladder, flipped_limit)[("m", "dt=0.01")] == "at stability limit"
    flipped_inside = [*ladder[:2], run(setting="dt=0.005", status="newton_failed")]
    assert verdict(ladder, flipped_inside)[("m", "dt=0.005")] == "differs"
    adaptive = [run(setting="rtol=1e-4")]
    assert verdict(adaptive, [run(setting="rtol=1e-4", status="max_steps")])[("m", "rtol=1e-4")] == "differs"


def test_fixed_step_runs_keep_their_steps_and_errors_to_round_off():
    base = [run(energy_error=1e-5)]
    assert verdict(base, [run(energy_error=1e-5 * (1 + 5e-3))]) == {("m", "dt=0.01"): "within tolerance"}
    assert verdict(base, [run(energy_error=1e-5 * (1 + 3e-2))]) == {("m", "dt=0.01"): "differs"}
    assert verdict(base, [run(steps=101)]) == {("m", "dt=0.01"): "differs"}
    # values at the floor's level (round-off, the reference's own error) differ freely
    assert verdict([run(energy_error=3e-11)], [run(energy_error=9e-11)]) == {("m", "dt=0.01"): "within tolerance"}
    assert verdict(base, [run(energy_error=np.nan)]) == {("m", "dt=0.01"): "differs"}


def test_adaptive_runs_may_move_a_few_steps_and_their_errors_by_a_factor_or_far_below_their_rtol():
    base = [run(setting="rtol=1e-6", steps=1000, energy_error=1e-7)]
    assert verdict(base, [run(setting="rtol=1e-6", steps=1025, energy_error=1.9e-7)]) == {("m", "rtol=1e-6"): "within tolerance"}
    assert verdict(base, [run(setting="rtol=1e-6", steps=1040, energy_error=1e-7)]) == {("m", "rtol=1e-6"): "differs"}
    assert verdict(base, [run(setting="rtol=1e-6", steps=1000, energy_error=3e-7)]) == {("m", "rtol=1e-6"): "differs"}
    # an error 50x smaller than its tolerance asks: its value is incidental, a factor 20 is fine
    small = [run(setting="rtol=1e-4", energy_error=2e-8)]
    assert verdict(small, [run(setting="rtol=1e-4", energy_error=4e-7)]) == {("m", "rtol=1e-4"): "within tolerance"}


def test_a_missing_row_breaks_the_statement_and_is_named():
    c = compare_runs(pd.DataFrame([run(), run("n")]), pd.DataFrame([run()]))
    assert not reproducible(c)
    assert statement(c).endswith("1 differ: `n` dt=0.01 on s (only in the first table).")


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match=re.escape("the second table has no column(s) steps")):
        compare_runs(pd.DataFrame([run()]), pd.DataFrame([run()]).drop(columns="steps"))
    with pytest.raises(ValueError, match="the first table has two rows for s/m/dt=0.01"):
        compare_runs(pd.DataFrame([run(), run()]), pd.DataFrame([run()]))
    with pytest.raises(ValueError, match=re.escape("adaptive_error_factor = 1.0 is invalid (allowed: a finite number > 1)")):
        AgreementTolerance(adaptive_error_factor=1.0)
    with pytest.raises(ValueError, match="fixed_error_rtol = -1"):
        AgreementTolerance(fixed_error_rtol=-1)
    with pytest.raises(ValueError, match="fixed_error_atol = nan"):
        AgreementTolerance(fixed_error_atol=float("nan"))
