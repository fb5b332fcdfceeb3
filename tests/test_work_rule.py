"""benchmark.work_rule: the flop rule against compiled floors (the measurement needs the floors'
directory and numba, outside the project; here its input checks and its verdicts)."""

import math

import pandas as pd
import pytest

from benchmark import work_rule


@pytest.mark.parametrize("argv, message", [
    (["--floor", "/nonexistent"], "error: --floor /nonexistent: no lgvi_nb.py, lgvi_nb2.py, rhs_nb.py there"),
])
def test_bad_input_is_refused_before_any_work(argv, message, capsys):
    assert work_rule.main(argv) == 2
    assert capsys.readouterr().err.startswith(message)


def test_bad_element_counts_are_refused(tmp_path, capsys):
    for f in ("lgvi_nb.py", "lgvi_nb2.py", "rhs_nb.py"):
        (tmp_path / f).write_text("")
    assert work_rule.main(["--floor", str(tmp_path), "--elements", "10,x"]) == 2
    assert "error: --elements '10,x' is invalid" in capsys.readouterr().err


def test_a_pair_agrees_within_a_factor_1_5_either_way():
    assert work_rule._within(1.49) and work_rule._within(1 / 1.49)
    assert not work_rule._within(1.51) and not work_rule._within(1 / 1.51)


def test_the_table_counts_the_pairs_within_the_tolerance():
    methods = pd.DataFrame([{"N": 10, "h": 2.5e-4, "method": m, "flops_compiled": f, "flops_lowered": f,
                             "old_flops": f, "floor_us": t, "newton_project": math.nan, "newton_floor": math.nan}
                            for m, f, t in (("lgvi", 3e3, 0.5), ("lie_rk4", 1.5e4, 2.0))])
    pairs = pd.DataFrame([{"N": 10, "pair": "lie_rk4 / lgvi", "floor_time_ratio": 4.0, "ratio_compiled": 5.0,
                           "agreement_compiled": 1.25, "within_compiled": True, "ratio_lowered": 2.0,
                           "agreement_lowered": 0.5, "within_lowered": False, "ratio_old": 1.8,
                           "agreement_old": 0.45, "within_old": False}])
    text = work_rule.markdown(methods, pairs, load="load average: 0.1", command="python -m benchmark.work_rule")
    assert "compiled program: **1 of 1**" in text and "lowered program: **0 of 1**" in text
    assert "earlier rule (evaluations × one isolated right-hand side): **0 of 1**" in text
    assert "load average: 0.1" in text
