"""Paired interleaved timing (`benchmark.answer.paired`): a known 1.3x ratio under noise is a winner
with the ratio inside its interval; two equal methods are a tie."""

import numpy as np
import pytest

from reelbench.benchmark.answer.paired import RACE_MARGIN, compare, pinned, resolved, time_paired


def synthetic(base: float, rng, load):
    """A "method" of ``base`` seconds, slowed by the round's shared load and its own noise."""
    def solve():
        return base * load[0] * rng.lognormal(0.0, 0.15)
    return solve


def shared_load(rng):
    """A load factor that changes between calls (as other processes come and go)."""
    load = [1.0]

    def tick():
        load[0] = float(np.clip(load[0] * rng.lognormal(0.0, 0.3), 0.3, 5.0))
    return load, tick


def run(bases: dict, seed: int):
    rng = np.random.default_rng(seed)
    load, tick = shared_load(rng)
    solves = {}
    for m, b in bases.items():
        f = synthetic(b, rng, load)
        solves[m] = (lambda f=f: (tick(), f())[1])
    return time_paired(solves, budget=1e9, max_rounds=3000, seed=seed)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_known_ratio_of_1_3_is_a_winner(seed):
    ratios = run({"fast": 1.0, "slow": 1.3}, seed)
    fast, slow = ratios
    assert fast.method == "fast" and fast.verdict == "winner" and slow.verdict == "slower"
    assert slow.low <= 1.3 <= slow.high and slow.low > 1.0
    # timed to the end and resolved, or left the race clearly slower than the tie margin
    assert (resolved(ratios) and slow.pairs >= 8) or (slow.low > 1 + RACE_MARGIN and resolved([fast]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_equal_methods_are_a_tie(seed):
    ratios = run({"a": 1.0, "b": 1.0}, seed)
    assert {r.verdict for r in ratios} == {"tie"}
    assert ratios[1].low <= 1.0 <= ratios[1].high


def test_the_budget_ends_the_timing():
    clock = iter(np.arange(0.0, 1e6, 1.0))
    rng = np.random.default_rng(0)
    ratios = time_paired({"a": lambda: rng.lognormal(0, 1.0), "b": lambda: rng.lognormal(0, 1.0)},
                         budget=12.0, clock=lambda: float(next(clock)))
    assert ratios[0].pairs < 20  # stopped by the clock, not resolved


def test_one_method_alone_is_its_own_winner_and_a_three_way_verdict():
    assert time_paired({"only": lambda: 1.0})[0].verdict == "winner"
    t = {"a": np.full(20, 1.0), "b": np.full(20, 1.02) * np.linspace(0.9, 1.1, 20), "c": np.full(20, 2.0)}
    out = {r.method: r.verdict for r in compare(t, np.random.default_rng(0))}
    assert out == {"a": "tie", "b": "tie", "c": "slower"}


def test_pinned_restores_the_affinity():
    import os

    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("no CPU affinity on this platform")
    before = os.sched_getaffinity(0)
    with pinned() as core:
        assert core is None or os.sched_getaffinity(0) == {core}
    assert os.sched_getaffinity(0) == before


def test_a_ratio_within_the_equivalence_margin_is_a_tie_whatever_its_interval():
    """Two quiet passes of the same settings moved a ratio by up to 10.7 %: an interval of
    [1.06, 1.16] in one pass (a 'winner' by its interval alone) was the fastest in the next."""
    from reelbench.benchmark.answer.paired import EQUIVALENCE, Ratio, verdicts

    out = verdicts([Ratio("a", 1.0, 1.0, 1.0, 1.0, 17), Ratio("b", 1.09, 1.09, 1.06, 1.16, 17)])
    assert [r.verdict for r in out] == ["tie", "tie"]
    out = verdicts([Ratio("a", 1.0, 1.0, 1.0, 1.0, 17), Ratio("b", 1.5, 1.5, 1.0 + EQUIVALENCE * 1.01, 1.6, 17)])
    assert [r.verdict for r in out] == ["winner", "slower"]


def _counting(base: float, calls: dict, name: str, rng):
    def solve():
        calls[name] = calls.get(name, 0) + 1
        return base * rng.lognormal(0.0, 0.05)
    return solve


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_race_drops_a_3x_slower_method_early_and_keeps_a_1_05x_one_to_the_end(seed):
    """Three synthetic methods: the fastest, one 5 % slower (a contender: within the tie margin)
    and one 3x slower. The 3x one leaves after the first rounds; the 1.05x one runs every round,
    as the fastest does; the verdicts are unchanged by the race."""
    rng = np.random.default_rng(seed)
    calls: dict = {}
    solves = {"fast": _counting(1.0, calls, "fast", rng), "close": _counting(1.05, calls, "close", rng),
              "slow": _counting(3.0, calls, "slow", rng)}
    ratios = {r.method: r for r in time_paired(solves, budget=1e9, max_rounds=60, precision=0.001, seed=seed)}
    assert calls["fast"] == calls["close"] == 60  # the contenders ran to the end
    assert calls["slow"] <= 5  # left at the first race check
    assert ratios["slow"].pairs == calls["slow"] and ratios["slow"].verdict == "slower"
    assert ratios["slow"].ratio == pytest.approx(3.0, rel=0.1)
    assert ratios["close"].ratio == pytest.approx(1.05, rel=0.03) and ratios["close"].verdict == "tie"
    assert resolved([ratios["fast"], ratios["close"]], 0.05)
