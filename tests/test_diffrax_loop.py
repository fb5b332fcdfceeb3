"""The diffrax methods' own compiled loop (integrators/diffrax_ode.py): it gives diffrax's
`diffeqsolve` results, a budgeted solve equals the unbudgeted one bit for bit however it is cut
into chunks, and one compiled program serves every budget, time limit and tolerance.

Short horizons and N = 4; the programs compiled here are shared by the tests of this module.
"""

from __future__ import annotations

import numpy as np
import pytest

from reelbench.integrators import get_integrator, lifecycle
from reelbench.integrators import diffrax_ode as dx
from reelbench.models import build_model, load_scene

T = 0.3
SAVE = 0.05


@pytest.fixture(scope="module")
def scene():
    return load_scene("fixed_length", elements=4)


def diffeqsolve(scene, name, t_save, **kw):
    """diffrax's own `diffeqsolve` of the same problem (no event: the run stays inside its guards)."""
    import diffrax as dfx

    from reelbench.integrators import rhs as _rhs

    model = build_model(scene)
    f = _rhs.ode_rhs(model, _rhs.DEFAULT_RHS)
    method = get_integrator(name)
    if "dt" in kw:
        controller, dt0, solver = dfx.ConstantStepSize(), kw["dt"], method.make_solver(None, None)
    else:
        controller = dfx.PIDController(rtol=kw["rtol"], atol=kw["atol"], dtmin=dx.DEFAULT_MIN_STEP_REL * T,
                                       force_dtmin=False)
        dt0, solver = None, method.make_solver(kw["rtol"], kw["atol"])
    sol = dfx.diffeqsolve(dfx.ODETerm(lambda t, y, args: f(t, y)), solver, t0=0.0, t1=T, dt0=dt0,
                          y0=np.asarray(model.initial_ode_state(), dtype=float), saveat=dfx.SaveAt(ts=t_save),
                          stepsize_controller=controller, max_steps=100_000, throw=False)
    return np.asarray(sol.ys), int(sol.stats["num_steps"]), int(sol.stats["num_accepted_steps"])


CASES = [("tsit5", dict(rtol=1e-6, atol=1e-8)), ("tsit5", dict(dt=2e-3)), ("dopri8", dict(rtol=1e-8, atol=1e-10)),
         ("dopri8", dict(dt=5e-3)), ("kvaerno5", dict(rtol=1e-6, atol=1e-8))]


@pytest.mark.parametrize("name,kw", CASES)
def test_the_loop_gives_diffeqsolves_results(scene, name, kw):
    """Same steps exactly, and the same saved states to round-off: the loop mirrors diffeqsolve's,
    but takes the scene's numbers as run-time arguments where diffeqsolve here has them as
    constants, which XLA folds. The last bits then differ and grow over the run (dopri8 at
    dt = 5e-3: 3.7e-12 relative), so the states are asserted to 1e-10 relative."""
    traj = get_integrator(name).solve(scene, T, save_every=SAVE, **kw)
    assert traj.ok, traj.reason
    lay = build_model(scene).layout
    ys, attempted, accepted = diffeqsolve(scene, name, traj.t, **kw)
    assert traj.stats["attempted_steps"] == attempted and traj.stats["steps"] == accepted
    for ours, theirs in ((traj.x, ys[:, lay.y_x]), (traj.velocity, ys[:, lay.y_w]), (traj.attitude, ys[:, lay.y_quat])):
        scale = np.max(np.abs(theirs))
        assert np.max(np.abs(ours - theirs)) <= 1e-10 * scale


def _same(a, b):
    assert a.status == b.status and a.reason == b.reason
    for k in ("steps", "rejected_steps", "attempted_steps", "rhs_evals", "event_time"):
        assert a.stats.get(k) == b.stats.get(k), k
    for x, y in ((a.t, b.t), (a.x, b.x), (a.velocity, b.velocity), (a.attitude, b.attitude), (a.work, b.work)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("name,kw,scene_name", [("tsit5", dict(rtol=1e-6, atol=1e-8), "fixed_length"),
                                                ("dopri8", dict(dt=5e-3), "fixed_length"),
                                                ("kvaerno5", dict(rtol=1e-6, atol=1e-8), "fixed_length"),
                                                ("tsit5", dict(rtol=1e-6, atol=1e-8), "retrieval_to_limit")])
def test_a_budgeted_solve_equals_the_unbudgeted_one_bit_for_bit(monkeypatch, scene, name, kw, scene_name):
    """With a time limit it never reaches, in one chunk or in many (a first chunk of 3 steps,
    then chunks sized to the clock), and with a length-limit event found inside a later chunk."""
    sc = scene if scene_name == "fixed_length" else load_scene(scene_name, elements=4)
    t_end = T if scene_name == "fixed_length" else None
    method = get_integrator(name)
    plain = method.solve(sc, t_end, save_every=SAVE, **kw)
    assert plain.status == ("ok" if scene_name == "fixed_length" else "length_limit"), plain.reason
    _same(plain, method.solve(sc, t_end, save_every=SAVE, time_limit=1e9, **kw))
    calls = []
    real = lifecycle.run_in_chunks

    def small_chunks(run, advance, total, first=lifecycle.FIRST_CHUNK):
        counted = lambda chunk: calls.append(chunk) or advance(chunk)  # noqa: E731
        return real(run, counted, total, first=3)

    monkeypatch.setattr(dx, "run_in_chunks", small_chunks)
    monkeypatch.setattr(lifecycle, "CHUNK_SECONDS", 1e-4)  # later chunks of a few steps too
    chunked = method.solve(sc, t_end, save_every=SAVE, time_limit=1e9, **kw)
    assert len(calls) >= 3, calls
    _same(plain, chunked)


def test_max_steps_is_the_same_with_and_without_a_time_limit(scene):
    method = get_integrator("tsit5")
    a = method.solve(scene, T, rtol=1e-6, atol=1e-8, save_every=SAVE, max_steps=40)
    assert a.status == "max_steps" and a.stats["attempted_steps"] == 40
    _same(a, method.solve(scene, T, rtol=1e-6, atol=1e-8, save_every=SAVE, max_steps=40, time_limit=1e9))


def test_a_spent_time_limit_keeps_the_saved_points(monkeypatch, scene):
    """The clock is read between chunks: a limit spent after the first chunk stops the run there
    with the points saved so far, which equal the full run's."""
    method = get_integrator("tsit5")
    full = method.solve(scene, T, rtol=1e-6, atol=1e-8, save_every=SAVE)
    real = lifecycle.run_in_chunks
    monkeypatch.setattr(dx, "run_in_chunks", lambda run, advance, total, first=0: real(run, advance, total, first=40))
    monkeypatch.setattr(lifecycle.Run, "out_of_time", lambda self: self.time_limit is not None)
    cut = method.solve(scene, T, rtol=1e-6, atol=1e-8, save_every=SAVE, time_limit=1.0)
    assert cut.status == "time_limit" and "stopped by time_limit" in cut.reason
    assert cut.stats["attempted_steps"] == 40 and 1 <= len(cut.t) < len(full.t)
    np.testing.assert_array_equal(cut.x, full.x[: len(cut.t)])


def test_one_program_serves_every_budget_time_limit_and_tolerance(monkeypatch, scene):
    """The compiled solve's key holds neither the budget nor the time limit: after the first
    solve of a mode, other tolerances, budgets and limits compile nothing."""
    monkeypatch.setattr(dx, "_SOLVES", lifecycle.CompileCache(maxsize=16))
    method = get_integrator("tsit5")
    first = method.solve(scene, T, rtol=1e-6, atol=1e-8, save_every=SAVE)
    n = len(dx._SOLVES)
    assert n == 1 and first.stats["compile_time"] > 0
    for kw in (dict(rtol=1e-5, atol=1e-7), dict(rtol=1e-6, atol=1e-8, max_steps=7),
               dict(rtol=1e-7, atol=1e-9, time_limit=30.0), dict(rtol=1e-6, atol=1e-8, max_steps=100, time_limit=1e9)):
        again = method.solve(scene, T, save_every=SAVE, **kw)
        assert again.stats["compile_time"] == 0.0, kw
    assert len(dx._SOLVES) == n and first.ok
    const = method.solve(scene, T, dt=2e-3, save_every=SAVE)  # constant step: its own program
    assert len(dx._SOLVES) == n + 1
    for kw in (dict(dt=1e-3), dict(dt=1e-4, max_steps=50), dict(dt=5e-3, time_limit=1e9)):
        assert method.solve(scene, T, save_every=SAVE, **kw).stats["compile_time"] == 0.0, kw
    assert len(dx._SOLVES) == n + 1 and const.ok
    assert not any(isinstance(part, str) and "timed" in part for key in dx._SOLVES._entries for part in key)
