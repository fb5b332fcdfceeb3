"""The stability map's logic (benchmark.studies.stability), without running integrators: the ladder,
skips, failure rows, and the generated reading. The map itself is results/stability/."""

import numpy as np
import pytest

from reelbench.benchmark.runs import runner
from reelbench.benchmark.studies import stability
from reelbench.benchmark.studies import stability_report
from reelbench.models import load_scene


def test_every_case_is_a_shipped_hard_scene_and_jobs_validate_names():
    for case in stability.CASES:
        load_scene(case.scene, **dict(case.overrides))
    jobs = stability.jobs_for()
    assert {j.case.scene for j in jobs} == {c.scene for c in stability.CASES}
    assert {(j.integrator, j.kind) for j in jobs} >= {("lgvi", "fixed"), ("tsit5", "fixed"), ("tsit5", "adaptive")}
    with pytest.raises(ValueError):
        stability.jobs_for(integrators=["no_such_method"])
    with pytest.raises(ValueError, match="no stability case"):
        stability.jobs_for(scenes=["fixed_length"])


def test_ladder_halves_from_the_top_and_keeps_ten_steps_per_run():
    case = next(c for c in stability.CASES if c.scene == "stiff_string")
    tasks = stability.ladder(case, "lgvi")
    dts = [t.dt for t in tasks]
    assert dts == sorted(dts, reverse=True)
    np.testing.assert_allclose(np.array(dts[:-1]) / np.array(dts[1:]), 2.0)
    assert all(t.t_end / t.dt >= 10 for t in tasks)


def test_ladder_stops_at_the_first_bounded_rung_and_failures_are_rows(monkeypatch):
    case = stability.Case("near_slack", 2.0)
    calls = []

    def fake_run_task(task, cache_dir=None, repeats=3, *, reference=True, finished=("ok",), budget=None):
        calls.append(task.dt)
        status = "ok" if task.dt <= 0.005 else "diverged"
        return {"dt": task.dt, "status": status, "reason": "" if status == "ok" else "energy", "steps": 2.0 / task.dt,
                "t_reached": 2.0, "setting": task.setting, "run_time": 0.1}

    monkeypatch.setattr(runner, "run_task", fake_run_task)
    row = stability.run_job(stability.Job(case, "lgvi", "fixed"))
    assert calls == [0.04, 0.02, 0.01, 0.005]
    assert row["largest_stable_dt"] == 0.005 and row["first_unstable_dt"] == 0.01
    assert row["unstable_status"] == "diverged" and row["bounded"] is True

    def broken(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(runner, "run_task", broken)
    row = stability.run_job(stability.Job(case, "rk45", "adaptive"))
    assert row["status"] == "error" and "boom" in row["reason"] and row["bounded"] is False


def test_skips_are_rows_with_reasons_and_explicit_requests_run_them():
    case = stability.Case("fixed_length", 0.1, skip=(lambda i: "too costly here" if i.name == "radau" else None,),
                          default_skip=(lambda i: "default run only" if i.name == "kvaerno5" else None,))
    row = stability.run_job(stability.Job(case, "radau", "adaptive"))
    assert row["status"] == "skipped" and row["reason"] == "too costly here" and row["bounded"] is False
    assert stability.run_job(stability.Job(case, "kvaerno5", "adaptive"))["status"] == "skipped"
    # naming a method on the command line is not the default run: default_skip does not apply
    assert all(j.default_run is False for j in stability.jobs_for(integrators=["kvaerno5"]))


def test_implicit_baselines_run_on_the_hard_scenes_by_default():
    """On the closed-form right-hand side the implicit baselines compile in seconds: the default
    map runs radau on every hard scene (shorter horizons where a dense LU per step dominates,
    with the reason) and kvaerno5 everywhere but on the two stiff, large ones."""
    for case in stability.CASES:
        assert stability.skip_reason(case, "radau") is None, case.scene
    assert sum(stability.skip_reason(c, "kvaerno5") is not None for c in stability.CASES) == 2
    many = next(c for c in stability.CASES if c.scene == "many_elements")
    horizon, why = stability._horizon(many, "radau")
    assert horizon < many.horizon and "Jacobian" in why
    # the horizons are chosen by declared capability, never by name: the LGVIs keep the case's
    assert all(stability._horizon(c, "lgvi", "fixed") == (c.horizon, "") for c in stability.CASES)
    assert all(callable(k if not isinstance(k, tuple) else k[0]) for c in stability.CASES for k in c.short)


def test_reading_is_generated_from_the_rows():
    df = stability.to_frame([
        {"scene": "stiff_string", "integrator": "lgvi", "kind": "fixed", "horizon": 0.2, "bounded": True,
         "largest_stable_dt": 1.25e-3, "rungs_tried": 6, "first_unstable_dt": 2.5e-3, "unstable_status": "diverged",
         "status": "ok", "run_time": 0.5, "energy_error": 1e-3},
        {"scene": "stiff_string", "integrator": "tsit5", "kind": "fixed", "horizon": 0.2, "bounded": True,
         "largest_stable_dt": 6.25e-4, "rungs_tried": 7, "status": "ok", "run_time": 1.0},
        {"scene": "stiff_string", "integrator": "rk45", "kind": "adaptive", "horizon": 0.2, "bounded": True,
         "status": "ok", "steps": 900, "run_time": 2.0, "median_step": 2e-4},
        {"scene": "stiff_string", "integrator": "radau", "kind": "adaptive", "horizon": 0.2, "bounded": False,
         "status": "skipped", "reason": "cost"},
    ])
    text = stability_report.reading(df)
    assert "dt = 0.00125 s" in text and "`diverged`" in text and "step ratio 2" in text
    # the compared pair follows from the declared capabilities (VARIATIONAL or not), not from names in code
    assert "(`lgvi` vs `tsit5`" in text and "is 2–2x" in text.split("**Robustness.**")[1]
    assert "`rk45`" in text and "left out" in text
    assert list(df.columns) == stability.COLUMNS


def test_a_length_limit_reached_too_soon_is_not_bounded():
    """On a length-limit scene a run counts as bounded only when it reaches its limit no earlier
    than the physics allows: an unstable step can throw the string to its limit in a few steps
    (crouch_grossman3 at 10 ms was seen at 0.05 s, against 1.10 s for every adaptive method)."""
    from reelbench.benchmark.studies.stability import CASES, is_bounded

    case = next(c for c in CASES if c.scene == "retrieval_to_limit")
    assert is_bounded(case, {"status": "length_limit", "t_reached": 1.146})
    assert not is_bounded(case, {"status": "length_limit", "t_reached": 0.0})
    assert not is_bounded(case, {"status": "diverged", "t_reached": 1.146})
    fast = next(c for c in CASES if c.scene == "fast_spin")
    assert is_bounded(fast, {"status": "ok", "t_reached": 2.0}) and fast.earliest_end == 0.0
