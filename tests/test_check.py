"""`python -m benchmark check`: the baseline comparison on a tiny sweep and on hand-made tables."""

import re
import shlex
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmark import check
from benchmark.metrics import ACCURACY
from integrators import registry

pytest.importorskip("integrators.scipy_ivp")
from integrators.scipy_ivp import RK45  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


class Sloppy(RK45):
    """RK45 whose tolerances can be loosened after the baseline was written: a degraded method."""

    name = "test_sloppy"
    loosen = 1.0

    def solve(self, scene, t_end=None, *, rtol=None, atol=None, **kw):
        return super().solve(scene, t_end, rtol=rtol * self.loosen, atol=atol * self.loosen, **kw)


@pytest.fixture
def sloppy():
    registry.register(Sloppy)
    yield Sloppy
    Sloppy.loosen = 1.0
    registry.unregister("test_sloppy")


def tiny(names):
    """Two tolerances on a 2-element fixed-length scene for 0.1 s: well under a second per run."""
    return check.build_check_tasks(names, scenes=["fixed_length"], t_end=0.1, overrides={"elements": 2})


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("cache"))  # one reference for the whole module


def run_check(cache, path, tasks, **kw):
    out = []
    code = check.main(baseline=path, tasks=tasks, executor="serial", cache_dir=cache, log=lambda s: None,
                      echo=out.append, **kw)
    return code, "\n".join(out)


# ------------------------------------------------------------------------------------------
# end to end on a tiny sweep

def test_unmodified_code_passes_bit_identically_against_the_baseline_it_wrote(tmp_path, cache, sloppy):
    path = tmp_path / "drift.csv"
    tasks = tiny(["test_sloppy"])
    assert run_check(cache, path, tasks, update=True)[0] == 0
    text = path.read_text()
    assert text.startswith("# reelbench drift baseline") and "Produced by `python -m benchmark check --update`" in text
    assert "Packages: numpy" in text and "test_sloppy rtol=0.0001 rtol=1e-06" in text
    code, report = run_check(cache, path, tasks)
    assert code == 0, report
    assert "3 rows compared" in report and "3 bit-identical" in report and "check passed" in report


def test_degraded_integrator_fails_naming_the_metric(tmp_path, cache, sloppy):
    path = tmp_path / "drift.csv"
    tasks = tiny(["test_sloppy"])
    run_check(cache, path, tasks, update=True)
    sloppy.loosen = 1e3  # same labels, 1000x looser tolerances
    code, report = run_check(cache, path, tasks)
    assert code == 1
    assert "REGRESSIONS" in report and "check FAILED" in report
    failed = report.split("## REGRESSIONS")[1].split("##")[0]
    assert re.search(r"\| fixed_length \| test_sloppy \| rtol=1e-06 \| energy_error \| [^|]+ \| [^|]+ \| x\d", failed), report
    assert "position_error_final" in failed
    # --update accepts the new numbers explicitly
    assert run_check(cache, path, tasks, update=True)[0] == 0
    assert run_check(cache, path, tasks)[0] == 0


def test_update_keeps_rows_of_integrators_it_did_not_run(tmp_path, cache, sloppy):
    path = tmp_path / "drift.csv"
    run_check(cache, path, tiny(["rk45"]), update=True)
    run_check(cache, path, tiny(["test_sloppy"]), update=True)
    table, _ = check.read_baseline(path)
    assert set(table["integrator"]) == {"rk45", "test_sloppy"}


def test_baseline_round_trips_bit_for_bit(tmp_path, cache):
    current = check.measure(tiny(["rk45"]), executor="serial", cache_dir=cache, log=lambda s: None)
    check.write_baseline(current, tmp_path / "b.csv")
    back, header = check.read_baseline(tmp_path / "b.csv")
    pd.testing.assert_frame_equal(back, current, check_exact=True, check_dtype=False)
    assert header[0].startswith("reelbench drift baseline")


def test_update_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "drift.csv"
    old = table(["ok"], energy_error=1e-6)
    check.write_baseline(old, path)
    before = path.read_text()

    def interrupted(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr("models.io.os.replace", interrupted)
    with pytest.raises(OSError, match="disk full"):
        check.write_baseline(table(["ok"], energy_error=5e-6), path)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["drift.csv"]  # no temporary left behind


# ------------------------------------------------------------------------------------------
# the rules, on hand-made tables (no integration)

def table(statuses, integrator="lgvi", order=None, **metrics):
    """A check table: one run row per status (settings dt=0.01, dt=0.005, ...), plus an order row."""
    rows = []
    for i, status in enumerate(statuses):
        row = {"scene": "fixed_length", "integrator": integrator, "setting": f"dt={0.01 / 2 ** i:g}", "status": status,
               "reason": "" if status == "ok" else "energy grew", "run_time": 0.01, "compile_time": 1.0}
        row.update({m: (1e-6 if status == "ok" else np.nan) for m in ACCURACY})
        if status == "ok":
            row.update(metrics)
        rows.append(row)
    if order is not None:
        rows.append({"scene": "fixed_length", "integrator": integrator, "setting": "order(dt)", "status": "",
                     "reason": "", check.ORDER: order})
    return pd.DataFrame(rows).reindex(columns=check.COLUMNS).fillna({"status": "", "reason": ""})


def regressed(cmp):
    return {(r["setting"], r["metric"]) for r in cmp.regressions}


def improved(cmp):
    return {(r["setting"], r["metric"]) for r in cmp.improvements}


def test_relative_factor_on_drifts_and_errors():
    base = table(["ok"], energy_error=1e-6, position_error_final=1e-5)
    assert not check.compare(base, table(["ok"], energy_error=1.9e-6, position_error_final=1e-5), registered=["lgvi"]).failed
    cmp = check.compare(base, table(["ok"], energy_error=2.1e-6), registered=["lgvi"])
    assert regressed(cmp) == {("dt=0.01", "energy_error")}
    assert cmp.regressions[0]["change"] == "x2.1"
    cmp = check.compare(base, table(["ok"], position_error_final=1e-6), registered=["lgvi"])
    assert not cmp.failed and improved(cmp) == {("dt=0.01", "position_error_final")}
    # a custom factor
    assert not check.compare(base, table(["ok"], energy_error=2.1e-6), check.Tolerance(factor=3), registered=["lgvi"]).failed


def test_round_off_metrics_have_an_absolute_floor():
    base = table(["ok"], orthogonality_error=5e-16, pi3_error=1e-14)
    noisy = table(["ok"], orthogonality_error=4e-13, pi3_error=2e-11)  # x800, x2000: still round-off
    cmp = check.compare(base, noisy, registered=["lgvi"])
    assert not cmp.failed and not cmp.improvements
    cmp = check.compare(base, table(["ok"], orthogonality_error=1e-9, pi3_error=1e-14), registered=["lgvi"])
    assert regressed(cmp) == {("dt=0.01", "orthogonality_error")}
    assert cmp.regressions[0]["allowed"] == "<= 1e-10"


def test_orders_are_compared_with_an_absolute_margin():
    base = table(["ok", "ok"], order=2.0)
    assert not check.compare(base, table(["ok", "ok"], order=1.6), registered=["lgvi"]).failed
    cmp = check.compare(base, table(["ok", "ok"], order=1.4), registered=["lgvi"])
    assert regressed(cmp) == {("order(dt)", check.ORDER)} and cmp.regressions[0]["change"] == "-0.60"
    assert improved(check.compare(base, table(["ok", "ok"], order=2.6), registered=["lgvi"])) == {("order(dt)", check.ORDER)}
    assert check.compare(base, table(["ok", "ok"], order=1.6), check.Tolerance(order_margin=0.2), registered=["lgvi"]).failed


def test_ok_to_not_ok_is_a_regression_and_the_reverse_an_improvement():
    cmp = check.compare(table(["ok", "ok"]), table(["ok", "diverged"]), registered=["lgvi"])
    assert regressed(cmp) == {("dt=0.005", "status")}
    assert cmp.regressions[0]["current"].startswith("diverged: energy grew")
    cmp = check.compare(table(["ok", "newton_failed"]), table(["ok", "ok"]), registered=["lgvi"])
    assert not cmp.failed and improved(cmp) == {("dt=0.005", "status")}
    # one failure for another: reported, not a regression
    cmp = check.compare(table(["newton_failed"]), table(["diverged"]), registered=["lgvi"])
    assert not cmp.failed and any("newton_failed -> diverged" in n for n in cmp.notes)


def test_missing_and_unregistered_integrators_are_reported_not_failed():
    base = pd.concat([table(["ok"]), table(["ok"], integrator="retired")], ignore_index=True)
    current = pd.concat([table(["ok"]), table(["ok"], integrator="new_plugin")], ignore_index=True)
    cmp = check.compare(base, current, registered=["lgvi", "new_plugin"])
    assert not cmp.failed
    assert any(n.startswith("new_plugin: no baseline, run `python -m benchmark check --update`") for n in cmp.notes)
    assert any(n.startswith("retired: in the baseline but no longer registered") for n in cmp.notes)
    report = check.format_report(cmp, check.Tolerance(), "drift.csv")
    assert "no baseline" in report and "check passed" in report


def test_baseline_integrator_that_fails_to_load_is_a_regression():
    base = pd.concat([table(["ok"]), table(["ok"], integrator="rk45")], ignore_index=True)
    cmp = check.compare(base, table(["ok"]), registered=["lgvi"], load_errors={"rk45": "ImportError: no scipy"})
    assert cmp.failed and cmp.regressions[0]["integrator"] == "rk45" and cmp.regressions[0]["metric"] == "load"
    assert "ImportError: no scipy" in cmp.regressions[0]["current"]


def test_update_replaces_an_unreadable_baseline(tmp_path, cache):
    path = tmp_path / "drift.csv"
    path.write_text("scene\nx\n")
    assert run_check(cache, path, tiny(["rk45"]), update=True)[0] == 0
    assert set(check.read_baseline(path)[0]["integrator"]) == {"rk45"}


def test_timing_never_fails():
    base = table(["ok"])
    slow = table(["ok"]).assign(run_time=100.0, compile_time=1000.0)
    cmp = check.compare(base, slow, registered=["lgvi"])
    assert not cmp.failed and cmp.timing["ratio"].iloc[0] == pytest.approx(1e4)


# ------------------------------------------------------------------------------------------
# bad input, before any work; the CI contract

def test_bad_input_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    from benchmark.cli import main

    monkeypatch.setattr(check, "measure", lambda *a, **k: pytest.fail("ran the sweep"))
    check.write_baseline(table(["ok"]), tmp_path / "b.csv")
    for args, message in [(["--factor", "1"], "--factor = 1.0 is invalid"),
                          (["--factor", "nan"], "--factor = nan is invalid"),
                          (["--order-margin", "-1"], "--order-margin = -1.0 is invalid"),
                          (["--jobs", "0"], "--jobs = 0 is invalid"),
                          (["--integrators", "lgvy"], "unknown integrator 'lgvy'"),
                          (["--baseline", str(tmp_path / "none.csv")], "none.csv does not exist")]:
        assert main(["check", "--baseline", str(tmp_path / "b.csv"), *args]) == 2, args
        assert message in capsys.readouterr().err, args
    (tmp_path / "bad.csv").write_text("# header only\nscene,integrator\nx,y\n")
    assert main(["check", "--baseline", str(tmp_path / "bad.csv")]) == 2
    assert "missing column(s) setting, status" in capsys.readouterr().err


def test_ci_runs_exactly_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    command = readme.split("Install and run the tests (the command CI runs):")[1].split("```bash\n")[1].split("\n```")[0]
    assert "python3 -m benchmark check" in command
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith("#")]
    assert command.strip() in ci, (command, ci)
    assert "\n" not in command.strip() and shlex.split(command)  # one shell line, well quoted
