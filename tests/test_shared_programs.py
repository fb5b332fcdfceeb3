"""One compiled program per method, model structure and N: the scene's numbers are run-time
arguments (`StringPendulum.values`, bound inside the program by `StringPendulum.bind`), so two
scenes that differ only in values share every compiled program, in the process and in JAX's
persistent compilation cache (the lowered programs are the same text).

`deployment` and `retrieval` differ in values only (retrieval adds `reel_control`, whose force
vanishes with u = 0 and which adds no state where the Carnot loss already carries W).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from reelbench.integrators import get_integrator

T_END = 0.2
DT = 0.002
ADAPTIVE = {"rtol": 1e-8, "atol": 1e-10}

#: (method, settings): every compiled kind of solve (fixed-step loop, diffrax constant and
#: adaptive, an implicit diffrax solve). scipy's methods call a right-hand side from the host,
#: one small program per model with its numbers folded in (`integrators.rhs.rhs_jit`: tested below)
METHODS = [
    ("lgvi", {"dt": DT}),
    ("lgvi_sym", {"dt": DT}),
    ("lie_rk4", {"dt": DT}),
    ("crouch_grossman3", {"dt": DT}),
    ("rattle", {"dt": DT}),
    ("tsit5", {"dt": DT}),
    ("tsit5", ADAPTIVE),
    ("dopri8", ADAPTIVE),
    ("kvaerno5", {"rtol": 1e-6, "atol": 1e-8}),
]

#: the largest relative difference allowed between a shared program's results and the results
#: of the scene's own program (they are the same program: identical in practice)
RTOL = 1e-12


def _clear_compiled() -> None:
    """Forget every compiled program of this process (the project's caches and JAX's)."""
    from reelbench.integrators import diffrax_ode, fixed_step, lgvi, lifecycle, rhs
    from reelbench.models._jax import jax

    for cache in (fixed_step._LOOPS, diffrax_ode._SOLVES, lgvi._MOMENTUM, lgvi._VELOCITY):
        cache.clear()
    rhs._TEMPLATES.clear()
    for cached in (rhs._rhs_program, rhs._jacobian_program, lifecycle._energy_error_program, lifecycle.energy_guard):
        cached.cache_clear()
    jax.clear_caches()


def _cache_sizes() -> tuple:
    from reelbench.integrators import diffrax_ode, fixed_step, lgvi, lifecycle, rhs

    return (len(fixed_step._LOOPS), len(diffrax_ode._SOLVES), len(lgvi._MOMENTUM), len(lgvi._VELOCITY),
            rhs._rhs_program.cache_info().currsize, rhs._jacobian_program.cache_info().currsize,
            lifecycle._energy_error_program.cache_info().currsize)


class _Compiles(logging.Handler):
    """Counts the programs JAX compiles (its log of compilations), whatever serves them."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.names: list[str] = []

    def emit(self, record):
        message = record.getMessage()
        if message.startswith("Compiling "):
            self.names.append(message.split(" with ", 1)[0])


def _counting_compiles(fn):
    from reelbench.models._jax import jax

    handler, logger = _Compiles(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            out = fn()
    finally:
        logger.removeHandler(handler)
    return out, handler.names


def _recording_lowered(monkeypatch) -> list[str]:
    """The text of every program compiled ahead of time from now on (what the persistent cache
    keys), until the next call."""
    from jax import stages

    monkeypatch.undo()  # one recorder at a time
    texts: list[str] = []
    compile_ = stages.Lowered.compile

    def compile(self, *args, **kwargs):
        texts.append(self.as_text())
        return compile_(self, *args, **kwargs)

    monkeypatch.setattr(stages.Lowered, "compile", compile)
    return texts


def _arrays(traj) -> dict:
    out = {"t": traj.t, "x": traj.x, "velocity": traj.velocity, "work": traj.work}
    if traj.attitude is not None:
        out["attitude"] = traj.attitude
    return {k: np.asarray(v, dtype=float) for k, v in out.items()}


def max_relative_difference(a, b) -> float:
    """max over the saved arrays of max|a − b| / max|b| (the trajectories must have one shape)."""
    A, B = _arrays(a), _arrays(b)
    assert A.keys() == B.keys()
    worst = 0.0
    for k in A:
        assert A[k].shape == B[k].shape, k
        scale = max(float(np.max(np.abs(B[k]))), 1e-300)
        worst = max(worst, float(np.max(np.abs(A[k] - B[k]))) / scale)
    return worst


def test_deployment_and_retrieval_differ_in_values_only():
    from reelbench.models import build_model, load_scene

    dep, ret = (build_model(load_scene(n)) for n in ("deployment", "retrieval"))
    assert dep.structure_key() == ret.structure_key()
    differ = {k for k, v in dep.values().items() if not np.array_equal(v, ret.values()[k])}
    assert "u" in differ  # retrieval's drum moment: a value, not a second program
    # a scene with another structure does not share: N, or the effects
    assert build_model(load_scene("deployment", elements=12)).structure_key() != dep.structure_key()
    assert build_model(load_scene("fixed_length")).structure_key() != dep.structure_key()


@pytest.mark.parametrize("name,settings", METHODS, ids=[f"{n}-{'dt' if 'dt' in s else 'rtol'}" for n, s in METHODS])
def test_two_scenes_share_one_program_and_its_results(name, settings, monkeypatch):
    method = get_integrator(name)

    def solve(scene):
        traj = method.solve(scene, t_end=T_END, **settings)
        assert traj.status == "ok", traj.reason
        return traj

    # deployment compiles; retrieval then compiles nothing at all
    _clear_compiled()
    lowered_dep = _recording_lowered(monkeypatch)
    shared_dep = solve("deployment")
    sizes = _cache_sizes()
    # the host's per-model setup (initial state and energy, the guards' bound) runs eager JAX
    # operations once per model: done first, so that what is counted is the solve's programs
    from reelbench.integrators import lifecycle
    from reelbench.models import build_model, load_scene

    ret_model = build_model(load_scene("retrieval"))
    ret_model.initial_state(), ret_model.initial_ode_state(), lifecycle.Guards.for_model(ret_model)
    shared_ret, compiled = _counting_compiles(lambda: solve("retrieval"))
    assert compiled == [], f"solving retrieval after deployment compiled {compiled}"
    assert _cache_sizes() == sizes
    assert shared_ret.stats["compile_time"] < 0.5 * shared_dep.stats["compile_time"] or shared_dep.stats["compile_time"] < 0.5

    # retrieval on its own (every compiled program forgotten) lowers the same programs, and
    # gives the same results; deployment then runs on retrieval's program
    _clear_compiled()
    lowered_ret = _recording_lowered(monkeypatch)
    own_ret = solve("retrieval")
    own_dep = solve("deployment")
    assert lowered_ret == lowered_dep  # the same text: one entry of the persistent cache
    if method.implementation == "jax-compiled":  # compiled ahead of time (scipy's are jitted)
        assert lowered_dep
    differences = (max_relative_difference(shared_ret, own_ret), max_relative_difference(shared_dep, own_dep))
    print(f"{name} {sorted(settings)}: max relative difference retrieval {differences[0]:.3g}, "
          f"deployment {differences[1]:.3g}")
    assert max(differences) <= RTOL
    # and the two scenes did differ
    assert max_relative_difference(shared_dep, shared_ret) > 1e-3


def test_the_right_hand_side_programs_lower_to_the_same_text():
    """The jitted right-hand side, its Jacobian (scipy's methods) and the energy guard: traced
    on either scene, the same program."""
    from reelbench.integrators import lifecycle, rhs
    from reelbench.models import build_model, load_scene

    models = [build_model(load_scene(n)) for n in ("deployment", "retrieval")]
    y0 = np.asarray(models[0].initial_ode_state())
    key = models[0].structure_key()
    for factory in (rhs._rhs_program.__wrapped__, rhs._jacobian_program.__wrapped__):
        texts = {factory(key, m, "closed_form").lower(m.values(), 0.0, y0).as_text() for m in models}
        assert len(texts) == 1
    texts = {lifecycle._energy_error_program.__wrapped__(key, m).lower(m.values(), y0, 0.0).as_text() for m in models}
    assert len(texts) == 1


def test_the_host_right_hand_side_folds_its_model_numbers_into_the_shared_program():
    """scipy's right-hand side and Jacobian: the structure's program with one model's numbers as
    constants (a call from the host is cheaper folded), equal to the shared program with those
    numbers as arguments, and one per model."""
    from reelbench.integrators import rhs
    from reelbench.models import build_model, load_scene

    models = [build_model(load_scene(n)) for n in ("deployment", "retrieval")]
    y0 = np.asarray(models[0].initial_ode_state())
    for jitted, shared in ((rhs.rhs_jit, rhs._rhs_program), (rhs.jacobian_jit, rhs._jacobian_program)):
        folded = [np.asarray(jitted(m)(0.0, y0)) for m in models]
        assert jitted(models[0]) is not jitted(models[1])
        for m, f in zip(models, folded):
            as_argument = np.asarray(rhs.program(shared, m, "closed_form")(rhs.device_values(m), 0.0, y0))
            assert np.max(np.abs(f - as_argument)) <= RTOL * np.max(np.abs(as_argument))
        assert np.max(np.abs(folded[0] - folded[1])) > 0  # the two scenes' numbers differ
