"""`python -m benchmark work-rule` (benchmark.work.work_rule): the flop rule against compiled floors
(the measurement needs the floors' directory and numba, outside the project; here its input
checks, its writing and its verdicts)."""

import math

import pandas as pd
import pytest

from reelbench.benchmark.cli.main import main
from reelbench.benchmark.work import work_rule


@pytest.mark.parametrize("argv, message", [
    (["--floor", "/nonexistent"], "error: argument --floor: '/nonexistent': no lgvi_nb.py, lgvi_nb2.py, rhs_nb.py there"),
])
def test_bad_input_is_refused_before_any_work(argv, message, capsys):
    assert main(["work-rule", *argv]) == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]


def test_bad_element_counts_are_refused(tmp_path, capsys):
    for f in ("lgvi_nb.py", "lgvi_nb2.py", "rhs_nb.py"):
        (tmp_path / f).write_text("")
    for elements, message in (("10,x", "argument --elements: 'x' is not an integer"),
                              ("10,1", "argument --elements: '10,1' is invalid (allowed: one or more integers >= 2")):
        assert main(["work-rule", "--floor", str(tmp_path), "--elements", elements]) == 2
        assert message in capsys.readouterr().err, elements
    assert main(["work-rule", "--floor", str(tmp_path), "--steps", "9"]) == 2
    assert "argument --steps: 9 is invalid (allowed: an integer >= 10" in capsys.readouterr().err


def test_work_rule_is_a_command_of_the_command_line(tmp_path, monkeypatch, capsys):
    """`python -m benchmark work-rule` measures (here replaced) and writes --out, headed by the command."""
    for f in ("lgvi_nb.py", "lgvi_nb2.py", "rhs_nb.py"):
        (tmp_path / f).write_text("")
    seen = {}
    monkeypatch.setattr(work_rule, "report", lambda floor, elements, steps, repeats, *, command:
                        seen.update(elements=elements, command=command) or "# table\n")
    out = tmp_path / "w.md"
    assert main(["work-rule", "--floor", str(tmp_path), "--elements", "10,40", "--out", str(out)]) == 0
    assert out.read_text() == "# table\n" and seen["elements"] == [10, 40]
    assert seen["command"].startswith("python -m benchmark work-rule --floor")


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
    text = work_rule.markdown(methods, pairs, load="load average: 0.1", command="python -m benchmark work-rule")
    assert "compiled program: **1 of 1**" in text and "lowered program: **0 of 1**" in text
    assert "earlier rule (evaluations × one isolated right-hand side): **0 of 1**" in text
    assert "load average: 0.1" in text


# --- the floors' own flops: counting scalars (benchmark.work.opcount) -----------------------------

def test_explicit_euler_on_a_linear_system_counts_what_a_hand_count_gives():
    """y <- y + h (A y) with a 2 x 2 A: per step 4 multiplications and 2 additions for A y, then 2
    multiplications (h ×) and 2 additions: 10 flops; 3 steps: 30, of which 18 multiplications."""
    from reelbench.benchmark.work.opcount import Counted, OpCounter, counted_array

    A = counted_array([[0.0, 1.0], [-1.0, 0.0]])
    y, h = counted_array([1.0, 0.0]), Counted(0.1)
    with OpCounter() as ops:
        for _ in range(3):
            f = [A[i, 0] * y[0] + A[i, 1] * y[1] for i in range(2)]
            y = [y[i] + h * f[i] for i in range(2)]
    assert ops.flops == 30 and ops.counts["mul"] == 18 and ops.counts["add"] == 12
    assert math.isclose(float(y[0]), 0.97) and math.isclose(float(y[1]), -0.299)  # the same numbers as floats


def test_a_numba_kernel_runs_as_plain_python_with_its_square_roots_and_allocations_counted(tmp_path):
    """A kernel written for numba (njit, np.zeros, math.sqrt, np.sqrt) is counted as written: its
    compile-time decoration is a no-op, its fresh arrays hold counting scalars, its roots count."""
    from reelbench.benchmark.work.opcount import OpCounter, counted_array, load_plain

    (tmp_path / "kern.py").write_text(
        "import math\nimport numpy as np\nfrom numba import njit\n\n"
        "@njit(cache=True)\ndef norms(x):\n"
        "    out = np.zeros(x.shape[0])\n"
        "    for i in range(x.shape[0]):\n"
        "        out[i] = math.sqrt(x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1]) + np.sqrt(x[i, 0] * x[i, 0]) / 2.0\n"
        "    return out\n")
    kern = load_plain(tmp_path, ("kern",))["kern"]
    with OpCounter([kern]) as ops:
        out = kern.norms(counted_array([[3.0, 4.0], [6.0, 8.0]]))
    # per row: 2 multiplications and an addition under the first root, 1 multiplication under
    # the second, a division and an addition
    assert dict(ops.counts) == {"mul": 6, "add": 4, "sqrt": 4, "div": 2}
    assert [float(v) for v in out] == [6.5, 13.0]
    import sys
    numba = sys.modules.get("numba")  # the stand-in is gone: absent, or the real one (it has a file)
    assert "kern" not in sys.modules and (numba is None or hasattr(numba, "__file__"))


def test_operations_outside_a_counter_are_not_counted():
    from reelbench.benchmark.work.opcount import Counted, OpCounter

    x = Counted(2.0)
    y = x * x
    with OpCounter() as ops:
        z = y + 1.0
        assert z > 4.0  # a comparison: tallied apart, not a flop
    _ = z * z
    assert ops.flops == 1 and ops.counts["cmp"] == 1


def test_the_table_says_what_the_floors_own_count_keeps():
    methods = pd.DataFrame([{"N": 160, "h": 1.6e-5, "method": m, "flops_lowered": f, "flops_compiled": f,
                             "old_flops": f, "floor_flops": ff, "lowered_per_floor_flop": f / ff, "floor_us": t,
                             "floor_gflop_s": ff / t / 1e3, "newton_project": math.nan, "newton_floor": math.nan}
                            for m, f, ff, t in (("lgvi", 1.3e4, 1.16e4, 2.19), ("lie_rk4", 8.1e4, 5.84e4, 18.0))])
    agreement = {"lowered": 0.75, "compiled": 2.19, "old": 0.60, "floor": 0.613, "floor_normalised": 0.62}
    pairs = pd.DataFrame([{"N": 160, "pair": "lie_rk4 / lgvi", "floor_time_ratio": 8.2,
                           **{f"agreement_{k}": v for k, v in agreement.items()},
                           **{f"within_{k}": work_rule._within(v) for k, v in agreement.items()},
                           "lowered_over_floor_flops": 0.75 / 0.613}])
    text = work_rule.markdown(methods, pairs, load="load average: 0.1", command="python -m benchmark work-rule")
    assert "the floors' own flops (counted exactly): **0 of 1**" in text
    assert "lowered program: **1 of 1**" in text and "compiled program: **0 of 1**" in text
    assert "run at 3.2–5.3 GFlop/s" in text and "(the farthest: lie_rk4 / lgvi at N = 160,\n0.613); counting ÷ and √ as 4 flops, 0 of 1." in text
    assert "| 160 | lie_rk4 / lgvi | 8.2 | 0.75 ✓ | 2.19 ✗ | 0.6 ✗ | 0.613 ✗ | 0.62 ✗ | 1.22 ✓ |" in text
    assert "Of the lowered count's 0 misses, 0 are pairs the floors' own count" in text
    assert "counts 1.1–1.4× the floor's flops" in text
