"""No compiled solve contains a host callback: the wall-clock budget is read between chunks on
the host, and equinox's runtime checks are off (``EQX_ON_ERROR=nan``, `models._jax`), so every
solve program is pure XLA (fast in XLA's fused loop, and cacheable by JAX's persistent cache).

Each registered compiled method's solve is lowered on a tiny scene, with a time limit (the
budgeted solve), and its StableHLO text is searched for a custom call to a Python callback.
"""

from __future__ import annotations

import re

import pytest

from reelbench.integrators import diffrax_ode, fixed_step, get_integrator
from reelbench.models import load_scene

COMPILED = {"lgvi": dict(dt=1e-3), "lgvi_sym": dict(dt=1e-3), "lgvi_yoshida4": dict(dt=1e-3),
            "lgvi_suzuki4": dict(dt=1e-3), "lie_rk4": dict(dt=1e-3), "crouch_grossman3": dict(dt=1e-3),
            "rattle": dict(dt=1e-3), "tsit5": dict(rtol=1e-6, atol=1e-8), "dopri5": dict(dt=1e-3),
            "dopri8": dict(rtol=1e-8, atol=1e-10), "kvaerno5": dict(rtol=1e-5, atol=1e-7)}

CALL = re.compile(r"custom_call\s*@\s*\"?([\w.]+)|call_target_name\s*=\s*\"([\w.]+)\"")


def callbacks(text: str) -> list[str]:
    """The custom-call targets of a lowered program that call back into Python."""
    return [a or b for a, b in CALL.findall(text) if "callback" in (a or b).lower()]


@pytest.fixture
def lowered(monkeypatch):
    """The StableHLO text of every program compiled ahead of time while the test runs (the solves
    compile through ``jit(...).lower(...).compile()``), from empty compile caches."""
    from reelbench.models._jax import jax

    texts = []
    real = jax.stages.Lowered.compile

    def recording(self, *args, **kwargs):
        texts.append(self.as_text())
        return real(self, *args, **kwargs)

    monkeypatch.setattr(jax.stages.Lowered, "compile", recording)
    for cache in (fixed_step._LOOPS, diffrax_ode._SOLVES):
        monkeypatch.setattr(cache, "_entries", type(cache._entries)())
    return texts


@pytest.mark.parametrize("name", sorted(COMPILED))
@pytest.mark.parametrize("scene_name", ["fixed_length", "deployment"])
def test_no_compiled_solve_contains_a_host_callback(lowered, name, scene_name):
    scene = load_scene(scene_name, elements=2)
    traj = get_integrator(name).solve(scene, 0.01, time_limit=60.0, **COMPILED[name])
    assert traj.ok, traj.reason
    assert lowered, "the solve compiled nothing ahead of time: this test no longer sees its program"
    for text in lowered:
        assert "stablehlo" in text and callbacks(text) == [], (name, callbacks(text))


def test_the_search_finds_a_callback_where_there_is_one(lowered):
    """Kvaerno5's opt-in counting replay keeps its counting callbacks (a separate program, not a
    timed solve): the search above would see them."""
    traj = get_integrator("kvaerno5").solve(load_scene("fixed_length", elements=2), 0.01, rtol=1e-5, atol=1e-7,
                                           count_evaluations=True)
    assert traj.ok and traj.stats["rhs_evals"] > 0
    assert [t for t in lowered if callbacks(t)] and [t for t in lowered if not callbacks(t)]
