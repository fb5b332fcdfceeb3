"""The plugin contract of an integrator, checked (`check_integrator`; the command is
`benchmark.contract.verify`).

An integrator (`check_integrator`) is checked on two small scenes (N = 3, 0.32 s), one at
fixed length and one reeling, against a tight DOP853 solution of the model's own equations
(scipy, not a plugin of this project):

* ``declarations``: name, capabilities, implementation, order (per situation where it declares
  ``orders``) and description are what the registry and the sweep read; a study setting that
  integrators once declared (`STUDY_SETTINGS`) is refused, since no study reads it any more;
* ``order <situation>``: the observed order of its last two step sizes (or, for an
  adaptive-only method, the slope of its error against its step count over five tolerances and
  1.28 s) is within `ORDER_TOLERANCE` of the declared one, with errors above round-off;
* ``arguments``: a bad step or tolerance raises ValueError before any work;
* ``budget``, ``length limit``, ``energy guard``: a run stopped by ``max_steps`` says so; a
  string that runs out stops ``length_limit`` inside the range; at a step too coarse to be
  stable (or its loosest tolerance) every saved point it returns as good is within the energy
  bound and finite, and a blow-up is a status other than ok;
* ``capability <name>``: each declared capability holds (fixed step / adaptive: the setting is
  taken and the other refused unless declared; group-preserving: ‖I − RᵀR‖ at round-off;
  variational: π3, conserved by the scene, kept to round-off and solver tolerance; implicit: it
  reports iterations);
* ``deterministic``: the same call twice gives the same trajectory, bit for bit;
* ``flops``: its work per step can be counted by the project's rule (`benchmark.work.flops`).

Small N and short horizons: a method takes seconds to tens of seconds (its compilations).
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np

from reelbench.benchmark.contract.checks import Check, ContractError, run_checks, small_scene
from reelbench.benchmark.core.order import fitted_order, last_order
from reelbench.benchmark.core.policy import VERIFY_REFERENCE, atol_for

#: the two situations an order is declared for, as small scenes (effects of the retrieval scene)
ORDER_SCENES = {
    "fixed_length": ("elasticity", "gravity", "rigid_body"),
    "reel": ("elasticity", "gravity", "rigid_body", "reel", "carnot", "reel_control"),  # ṡ_p(0) = −0.7 m/s
}
T_END, SAVE_EVERY = 0.32, 0.08
#: fixed steps: the last pair is in the asymptotic range of every shipped method of declared order
#: below `HIGH_ORDER` with errors above round-off (tests/test_orders.py)
STEPS = (0.008, 0.004, 0.002)
#: fixed steps of a method declaring order `HIGH_ORDER` or more in the situation: at `STEPS` an
#: eighth-order error is round-off already at 8 ms (dopri8: 1.1e-14, 1.4e-14, 1.1e-14), so its
#: order cannot be observed there; these are tests/test_orders.py's steps for dopri8 (errors
#: 6.3e-9, 1.5e-11, 2.0e-12 at fixed length, 6.8e-9, 1.7e-11, 2.2e-12 reeling), each dividing
#: `SAVE_EVERY`; the ladder is chosen by the declared order, as `benchmark.studies.orders.coarsest_step` does
HIGH_ORDER, HIGH_ORDER_STEPS = 6, (0.04, 0.02, 0.016)
#: tolerances of an adaptive-only method, over a longer horizon (more steps): its observed order
#: is the least-squares slope of log error against log steps over all five (pairwise slopes of
#: DOP853 scatter from 6.8 to 11.9 here, as its step counts change by a few; the fit gives 8.6)
RTOLS = (1e-5, 1e-6, 1e-7, 1e-8, 1e-9)
ADAPTIVE_T_END = 1.28
#: |observed − declared| allowed for a fixed step; an adaptive method's slope is looser (its step
#: sequence changes with the tolerance), so it gets twice this
ORDER_TOLERANCE = 0.45
#: A method may converge up to one order faster over so few steps (a local error of order p + 1
#: that has not yet accumulated to O(h^p): dopri8 measures 9.0 here)
ABOVE = 1.0
#: errors below this are round-off, too small to measure an order by
ROUND_OFF = 1e-12
#: an attitude kept on SO(3) to round-off, and π3 kept by a variational method to its solver's
#: tolerance (measured relative drifts: the LGVIs 5e-15, RATTLE 9.1e-10 from its Newton tolerance)
GROUP_TOLERANCE, PI3_TOLERANCE = 1e-11, 1e-8


#: What an integrator class once declared about the studies that run it, and where each study
#: now keeps that choice (keyed by method name): a plugin that still declares one would be
#: silently ignored.
STUDY_SETTINGS = {
    "default_sweep": "benchmark.runs.sweep.EXTENDED_METHODS (a plugin joins the sweep by --integrators or "
                     "--with-plugins)",
    "sweep_rtols": "benchmark.runs.sweep.SWEEP_RTOLS",
    "paper_settings": "benchmark.runs.sweep.PAPER_METHOD",
    "horizon_settings": "benchmark.studies.horizon.SETTINGS",
    "expensive": "benchmark.studies.stability.EXPENSIVE",
}


@functools.lru_cache(maxsize=8)
def _reference(effects: tuple, t_end: float = T_END):
    """A tight DOP853 solution (scipy on the model's closed-form equations) at the save points."""
    from scipy.integrate import solve_ivp

    from reelbench.integrators import Trajectory
    from reelbench.integrators.rhs import rhs_jit
    from reelbench.models import build_model

    scene = small_scene(effects)
    model = build_model(scene)
    lay, f = model.layout, rhs_jit(model)
    t_eval = np.linspace(0.0, t_end, int(round(t_end / SAVE_EVERY)) + 1)
    sol = solve_ivp(lambda t, y: np.asarray(f(t, y)), (0.0, t_end), np.asarray(model.initial_ode_state()),
                    t_eval=t_eval, **VERIFY_REFERENCE)
    if sol.status != 0:
        raise RuntimeError(f"the reference failed: {sol.message}")
    y = sol.y.T
    return scene, Trajectory(t=sol.t, x=y[:, lay.y_x], attitude=y[:, lay.y_quat] if lay.has_attitude else None,
                             attitude_kind="quaternion", velocity=y[:, lay.y_w],
                             work=y[:, lay.y_work][:, 0] if lay.has_work else np.zeros(len(sol.t)))


def _method(integrator):
    """(instance, a context that keeps it registered for the checks) of a name, class or instance."""
    from reelbench.integrators import Integrator, get_integrator, registry

    if isinstance(integrator, str):
        return get_integrator(integrator), None
    cls = integrator if isinstance(integrator, type) else type(integrator)
    if not issubclass(cls, Integrator):
        raise TypeError(f"{integrator!r} is not an integrators.Integrator (subclass or instance)")
    temporary = cls.name and registry._REGISTRY.get(cls.name) is None
    if temporary:
        registry.register(cls)  # the flop count and the sweep find methods by name
    return (integrator if not isinstance(integrator, type) else cls()), (cls.name if temporary else None)


def check_integrator(integrator, *, log: Callable[[str], None] | None = None, raise_on_failure: bool = True
                     ) -> list[Check]:
    """Check an integrator (a registered name, an `Integrator` subclass or instance) against
    the contract; returns the checks, and raises `ContractError` if one fails (unless
    ``raise_on_failure`` is False). ``log`` gets each check's line as it is made."""
    from reelbench.integrators import registry

    integ, temporary = _method(integrator)
    try:
        checks = run_checks(_integrator_checks(integ), log)
    finally:
        if temporary:
            registry.unregister(temporary)
    if raise_on_failure and not all(c.ok for c in checks):
        raise ContractError(f"integrator {integ.name!r}", checks)
    return checks


def _integrator_checks(integ) -> list[tuple[str, Callable]]:
    runs: dict = {}  # the order runs, shared with the later checks
    steps = [("declarations", lambda: _declarations(integ))]
    for key in ORDER_SCENES:
        steps.append((f"order {key}", functools.partial(_order, integ, key, runs)))
    steps += [("arguments", lambda: _arguments(integ)),
              ("budget", lambda: _budget(integ)),
              ("length limit", lambda: _length_limit(integ)),
              ("energy guard", lambda: _energy_guard(integ))]
    for cap in sorted(integ.capabilities, key=lambda c: c.value):
        steps.append((f"capability {cap.value}", functools.partial(_capability, integ, cap, runs)))
    steps += [("deterministic", lambda: _deterministic(integ, runs)),
              ("flops", lambda: _flops(integ, runs))]
    return steps


def _setting(integ, k: int = 1) -> dict:
    """The k-th setting of the order ladder (a fixed step if the method takes one, else a tolerance)."""
    from reelbench.integrators import Capability

    if integ.has(Capability.FIXED_STEP):
        return {"dt": STEPS[k]}
    return {"rtol": RTOLS[k], "atol": atol_for(RTOLS[k])}


def _declarations(integ) -> Check:
    from reelbench.integrators import Capability
    from reelbench.integrators.base import SITUATIONS

    problems = []
    if not isinstance(integ.name, str) or not integ.name:
        problems.append("no name")
    caps = integ.capabilities
    if not caps or not all(isinstance(c, Capability) for c in caps):
        problems.append(f"capabilities {set(caps)!r} are not integrators.Capability members")
    elif not (Capability.FIXED_STEP in caps or Capability.ADAPTIVE in caps):
        problems.append("neither fixed_step nor adaptive: the sweep would give it no setting")
    if not isinstance(integ.order, int) or integ.order < 1:
        problems.append(f"order {integ.order!r} is not an integer >= 1")
    if set(integ.orders or {}) - set(SITUATIONS):
        problems.append(f"orders keyed by {sorted(set(integ.orders) - set(SITUATIONS))}; allowed {SITUATIONS}")
    if not isinstance(integ.implementation, str) or not integ.implementation:
        problems.append("no implementation (e.g. 'jax-compiled')")
    if not integ.description:
        problems.append("no description (shown by `list`)")
    for name, where in STUDY_SETTINGS.items():
        if hasattr(integ, name):
            problems.append(f"declares {name}, which no study reads: each study chooses its settings by method "
                            f"name ({where}); remove it")
    orders = ", ".join(f"{k} {integ.order_for(small_scene(e))}" for k, e in ORDER_SCENES.items())
    return Check("declarations", not problems, "; ".join(problems) if problems else
                 f"order {orders}; capabilities {', '.join(sorted(c.value for c in caps))}; {integ.implementation}")


def _error(traj, ref) -> float:
    return float(np.abs(np.asarray(traj.x) - ref.x).max())


def _order(integ, key: str, runs: dict) -> Check:
    from reelbench.integrators import Capability

    fixed = integ.has(Capability.FIXED_STEP)
    t_end = T_END if fixed else ADAPTIVE_T_END
    scene, ref = _reference(ORDER_SCENES[key], t_end)
    declared = integ.order_for(scene)
    name = f"order {key}"
    ladder = HIGH_ORDER_STEPS if declared >= HIGH_ORDER else STEPS
    settings = [{"dt": h} for h in ladder] if fixed else [{"rtol": r, "atol": atol_for(r)} for r in RTOLS]
    errs, sizes, trajs = [], [], []
    for s in settings:
        tr = integ.solve(scene, t_end=t_end, save_every=SAVE_EVERY, **s)
        trajs.append(tr)
        if not tr.ok:
            return Check(name, False, f"status {tr.status} at {_words(s)}: {tr.reason}")
        if len(tr.t) != len(ref.t) or not np.allclose(tr.t, ref.t, atol=1e-12):
            return Check(name, False, f"saved at {np.round(tr.t, 6).tolist()}, not at the save times "
                                      f"{ref.t.tolist()} (integrators.save_times)")
        errs.append(_error(tr, ref))
        sizes.append(s["dt"] if "dt" in s else 1.0 / max(float(tr.stats.get("steps", 0) or 0), 1.0))
    runs[key] = (scene, settings, trajs)
    e, h = np.array(errs), np.array(sizes)
    if e[-1] < ROUND_OFF:
        return Check(name, False, f"errors {_fmt(e)} reach round-off: the order cannot be observed at "
                                  f"{_words(settings[-1])} (an order this high is not measurable by these settings)")
    # fixed steps: the last halving; adaptive: the least-squares slope against log(1 / steps)
    observed = last_order(h, e) if fixed else fitted_order(h, e)
    tol = ORDER_TOLERANCE * (1 if fixed else 2)
    ok = declared - tol < observed < declared + ABOVE + tol
    how = ("dt " + ", ".join(f"{s['dt']:g}" for s in settings) if "dt" in settings[0]
           else "rtol " + ", ".join(f"{s['rtol']:g}" for s in settings) + f" (steps {[int(t.stats.get('steps', 0)) for t in trajs]})")
    return Check(name, ok, f"observed {observed:.2f}, declared {declared} (errors {_fmt(e)} at {how})")


def _fmt(values) -> str:
    return ", ".join(f"{v:.2g}" for v in values)


def _words(setting: dict) -> str:
    return ", ".join(f"{k} = {v:g}" for k, v in setting.items())


def _arguments(integ) -> Check:
    from reelbench.integrators import Capability

    scene = small_scene(ORDER_SCENES["fixed_length"])
    bad = []
    if integ.has(Capability.FIXED_STEP):
        bad += [{"dt": -0.01}, {"dt": 2 * T_END}]
    if integ.has(Capability.ADAPTIVE):
        bad += [{"rtol": 2.0, "atol": 1e-6}, {"rtol": -1e-6, "atol": 1e-8}]
    bad.append({})  # no setting at all
    refused = []
    for args in bad:
        try:
            tr = integ.solve(scene, t_end=T_END, **args)
        except ValueError:
            refused.append(args)
            continue
        return Check("arguments", False, f"solve({_words(args) or 'no setting'}) returned status {tr.status} "
                                         "instead of raising ValueError before any work")
    return Check("arguments", True, f"{len(refused)} bad settings refused with ValueError "
                                    f"({'; '.join(_words(a) or 'no setting' for a in refused)})")


def _finite(traj) -> bool:
    parts = (traj.t, traj.x, traj.attitude, traj.velocity, traj.momentum, traj.work)
    return all(a is None or np.all(np.isfinite(np.asarray(a, dtype=float))) for a in parts)


def _budget(integ) -> Check:
    from reelbench.integrators import Status

    scene = small_scene(ORDER_SCENES["fixed_length"])
    tr = integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, max_steps=3, **_setting(integ, 2))
    ok = tr.status == Status.MAX_STEPS.value and bool(tr.reason) and len(tr.t) >= 1 and _finite(tr)
    return Check("budget", ok, f"max_steps = 3: status {tr.status} ({tr.reason or 'no reason given'}), "
                               f"{len(tr.t)} saved point(s) kept{'' if _finite(tr) else ', NOT FINITE'}")


def _length_limit(integ) -> Check:
    """A string paid out from near its end runs out within 0.3 s: every correct method stops there."""
    from reelbench.integrators import Status
    from reelbench.models import build_model

    scene = small_scene(ORDER_SCENES["reel"], deployed_length=38.8, reel_rate=-1.5, control_moment=0.0)
    model = build_model(scene)
    tr = integ.solve(scene, t_end=0.8, save_every=0.02, **_setting(integ, 1))
    ell = model.L - np.asarray(tr.x)[:, 0]
    inside = bool(np.all(ell < model.L - model.b)) and _finite(tr)
    ok = tr.status == Status.LENGTH_LIMIT.value and inside
    at = tr.stats.get("event_time")
    return Check("length limit", ok, f"status {tr.status}" + (f" at t = {at:.3g} s" if at is not None else "")
                 + f", longest saved ℓ {model.L - model.b - ell.max():.2g} m short of L − b = {model.L - model.b:g} m"
                 + ("" if inside else ": a saved point is outside the range"))


def _energy_guard(integ) -> Check:
    """At a coarse setting the kept points must be finite and within the energy bound, and a
    run that leaves it must not be ok."""
    from reelbench.integrators import Capability, Guards
    from reelbench.models import build_model, load_scene
    from reelbench.models.diagnostics import evaluate

    scene = load_scene("fixed_length", elements=10)
    model = build_model(scene)
    bound = Guards.for_model(model).energy_bound
    setting = {"dt": 0.02} if integ.has(Capability.FIXED_STEP) else {"rtol": 1e-2, "atol": 1e-4}
    tr = integ.solve(scene, t_end=1.0, save_every=0.02, **setting)
    if not _finite(tr):
        return Check("energy guard", False, f"status {tr.status} at {_words(setting)} returned non-finite values")
    df = evaluate(scene, tr)
    worst = float(np.max(np.abs(df["energy_minus_work"] - df["energy_minus_work"].iloc[0])))
    within = worst <= bound * (1 + 1e-9)
    ok = within and (tr.ok or (bool(tr.reason) and not tr.ok))
    return Check("energy guard", ok, f"{_words(setting)}: status {tr.status} after {len(tr.t)} saved point(s), "
                                     f"largest |E − W − E0| kept {worst:.3g} J of the bound {bound:.3g} J"
                 + ("" if within else ": a point beyond the bound returned as good"))


def _capability(integ, cap, runs: dict) -> Check:
    from reelbench.integrators import Capability
    from reelbench.models.diagnostics import evaluate

    name = f"capability {cap.value}"
    scene, settings, trajs = runs.get("fixed_length") or (None, None, None)
    if cap in (Capability.FIXED_STEP, Capability.ADAPTIVE):
        other = Capability.ADAPTIVE if cap is Capability.FIXED_STEP else Capability.FIXED_STEP
        scene = small_scene(ORDER_SCENES["fixed_length"])
        setting = {"dt": 0.004} if cap is Capability.FIXED_STEP else {"rtol": 1e-6, "atol": 1e-8}
        tr = integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, **setting)
        if not tr.ok:
            return Check(name, False, f"solve({_words(setting)}) ended {tr.status}: {tr.reason}")
        if integ.has(other):
            return Check(name, True, f"takes {_words(setting)} (status ok); also declares {other.value}")
        refused = {"rtol": 1e-6, "atol": 1e-8} if cap is Capability.FIXED_STEP else {"dt": 0.004}
        try:
            integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, **refused)
        except ValueError:
            return Check(name, True, f"takes {_words(setting)}; refuses {_words(refused)} (not {other.value})")
        return Check(name, False, f"accepts {_words(refused)} without declaring {other.value}")
    if trajs is None:
        return Check(name, False, "no run on the fixed-length scene to judge it by (its order check failed)")
    sums = [evaluate(scene, t) for t in trajs]
    if cap is Capability.GROUP_PRESERVING:
        worst = max(float(d["orthogonality_error"].max()) for d in sums)
        kind = trajs[0].attitude_kind
        return Check(name, worst < GROUP_TOLERANCE, f"largest ‖I − RᵀR‖ {worst:.2g} ({kind} attitude; "
                                                    f"round-off is below {GROUP_TOLERANCE:g})")
    if cap is Capability.VARIATIONAL:
        # π3 is a momentum map of this scene's symmetry: a variational method keeps it exactly
        worst = max(float(np.max(np.abs(d["pi3"] - d["pi3"].iloc[0])) / max(abs(d["pi3"].iloc[0]), 1e-300))
                    for d in sums)
        return Check(name, worst < PI3_TOLERANCE, f"relative π3 drift {worst:.2g} (allowed {PI3_TOLERANCE:g}, "
                                                  "round-off and solver tolerance; a method that is not variational "
                                                  "drifts with its truncation error)")
    if cap is Capability.IMPLICIT:
        counters = ("newton_iterations", "jac_evals", "lu_decompositions")
        tr = _counted(integ, scene, settings[-1], trajs[-1])
        seen = {k: tr.stats.get(k) for k in counters if tr.stats.get(k)}
        return Check(name, bool(seen), ", ".join(f"{k} {v:g}" for k, v in seen.items()) if seen else
                     f"reports none of {', '.join(counters)}: its solves cannot be counted")
    return Check(name, True, "no check defined for this capability")


def _deterministic(integ, runs: dict) -> Check:
    scene = small_scene(ORDER_SCENES["fixed_length"])
    setting = _setting(integ, 1)
    a = integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, **setting)
    b = integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, **setting)
    fields = ("t", "x", "attitude", "velocity", "momentum", "work")
    differ = [f for f in fields if not ((getattr(a, f) is None and getattr(b, f) is None)
                                        or np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f))))]
    same_status = a.status == b.status and a.stats.get("steps") == b.stats.get("steps")
    return Check("deterministic", not differ and same_status,
                 f"two calls at {_words(setting)}: " + ("identical trajectories, statuses and step counts" if
                                                        not differ and same_status else
                                                        f"differ in {', '.join(differ) or 'status or steps'}"))


def _counted(integ, scene, setting: dict, traj):
    """``traj``, or where a plain run cannot count its work (``stats["counts_unavailable"]``) the
    same run with the counting replay the lifecycle offers (``count_evaluations=True``), if the
    method takes that option."""
    if not traj.stats.get("counts_unavailable"):
        return traj
    try:
        return integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, count_evaluations=True, **setting)
    except ValueError:  # the method has no counting replay: its counts stay unavailable
        return traj


def _flops(integ, runs: dict) -> Check:
    from reelbench.benchmark.work.flops import run_flops
    from reelbench.models import build_model

    scene, settings, trajs = runs.get("fixed_length") or (None, None, None)
    if trajs is None:
        scene, settings = small_scene(ORDER_SCENES["fixed_length"]), None
        trajs = [integ.solve(scene, t_end=T_END, save_every=SAVE_EVERY, **_setting(integ, 1))]
    tr = _counted(integ, scene, settings[-1] if settings else _setting(integ, 1), trajs[-1])
    flops, note = run_flops(integ.name, build_model(scene), tr.stats, tr.stats.get("rhs"))
    steps = float(tr.stats.get("steps") or 0)
    ok = bool(np.isfinite(flops) and flops > 0 and steps > 0)
    per = f"{flops / steps:.3g} flops per step ({note})" if ok else note
    return Check("flops", ok, per)
