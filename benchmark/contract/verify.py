"""The plugin contract, checked: ``python -m benchmark verify NAME`` and its importable twins.

In the spirit of scikit-learn's ``check_estimator``: a plugin author (or this project's own
test suite) runs one function on an integrator or an effect and gets one `Check` per rule of
the contract (integrators/README.md, "The plugin contract"; models/README.md, "Adding an
effect"), each with the figure it was judged by::

    from reelbench.benchmark.contract.verify import check_integrator, check_effect
    check_integrator("my_method")          # raises ContractError naming every failed check
    check_effect("tip_spring", scene="my_scene.toml")

An integrator (`check_integrator`) is checked on two small scenes (N = 3, 0.32 s), one at
fixed length and one reeling, against a tight DOP853 solution of the model's own equations
(scipy, not a plugin of this project):

* ``declarations``: name, capabilities, implementation, order (per situation where it declares
  ``orders``) and description are what the registry and the sweep read;
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

An effect (`check_effect`) is checked in a scene that lists it:

* ``declarations``: its needs are registered, a dissipative effect has forces, forces imply
  ``forcing`` (their work W is carried) and a claimed ``power``;
* ``gradient <term>``: each potential term's closed-form gradient equals autodiff of its energy;
* ``power``: its forces' Q·w equals the power it claims (`power`; for its body loads
  `body_power`, the moment's Ω·M included), ≤ 0 when it says it is dissipative, and string
  forces leave Ω alone;
* ``energy balance``: DOP853 on the closed-form equations keeps E − W (E without forces) to
  `ENERGY_TOLERANCE` of the largest kinetic energy;
* ``scene keys``: each of its keys is refused with a message naming it when it breaks its rule,
  is missing where required, or is given without the effect.

Small N and short horizons: a method takes seconds to tens of seconds (its compilations).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np

from reelbench.benchmark.core.order import fitted_order, last_order
from reelbench.benchmark.core.policy import VERIFY_BALANCE_REFERENCE, VERIFY_REFERENCE, atol_for

#: the two situations an order is declared for, as small scenes (effects of the retrieval scene)
ORDER_SCENES = {
    "fixed_length": ("elasticity", "gravity", "rigid_body"),
    "reel": ("elasticity", "gravity", "rigid_body", "reel", "carnot", "reel_control"),  # ṡ_p(0) = −0.7 m/s
}
ELEMENTS, T_END, SAVE_EVERY = 3, 0.32, 0.08
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
#: |E − W − E0| / max T allowed of the reference on an effect's scene
ENERGY_TOLERANCE = 1e-7
#: an attitude kept on SO(3) to round-off, and π3 kept by a variational method to its solver's
#: tolerance (measured relative drifts: the LGVIs 5e-15, RATTLE 9.1e-10 from its Newton tolerance)
GROUP_TOLERANCE, PI3_TOLERANCE = 1e-11, 1e-8


@dataclass(frozen=True)
class Check:
    """One rule of the contract: its name, whether it holds, and the figure it was judged by."""

    name: str
    ok: bool
    figure: str

    def line(self) -> str:
        return f"{'ok  ' if self.ok else 'FAIL'}  {self.name}: {self.figure}"


class ContractError(AssertionError):
    """Raised by `check_integrator` / `check_effect` when a check fails; ``checks`` holds all of them."""

    def __init__(self, what: str, checks: list[Check]):
        self.checks = checks
        failed = [c for c in checks if not c.ok]
        super().__init__(f"{what} fails {len(failed)} of {len(checks)} checks:\n"
                         + "\n".join(c.line() for c in failed))


def _run_checks(steps: list[tuple[str, Callable]], log) -> list[Check]:
    """Run each (name, check) in turn; a check that raises fails with the exception as its figure."""
    import time

    out = []
    for name, fn in steps:
        t0 = time.perf_counter()
        try:
            got = fn()
        except Exception as exc:  # a broken hook is a failed check, not a crash of verify
            got = [Check(name, False, f"raised {type(exc).__name__}: {str(exc).splitlines()[0][:300] if str(exc) else ''}")]
        seconds = time.perf_counter() - t0
        for c in got if isinstance(got, list) else [got]:
            out.append(c)
            if log:
                log(f"{c.line()} ({seconds:.1f} s)")
    return out


# ------------------------------------------------------------------------------------------
# Integrators
# ------------------------------------------------------------------------------------------
def small_scene(effects, elements: int = ELEMENTS, **overrides):
    """The retrieval scene reduced to ``effects`` (values adjusted to stay valid): a short,
    small scene that moves every coordinate."""
    from reelbench.models import load_scene

    kw = dict(effects=list(effects), elements=elements, tip_velocity=[0.3, 1.0, -0.2], reel_rate=0.0,
              angular_velocity=[0.4, -0.3, 0.8] if "rigid_body" in effects else [0.0, 0.0, 0.0])
    if "reel_control" not in effects:
        kw["control_moment"] = 0.0
    if "reel" in effects:
        kw["reel_rate"] = -0.7
    kw.update(overrides)
    return load_scene("retrieval", **kw)


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
        checks = _run_checks(_integrator_checks(integ), log)
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


# ------------------------------------------------------------------------------------------
# Effects
# ------------------------------------------------------------------------------------------
def effect_scene(name: str, scene=None, overrides: dict | None = None):
    """The scene an effect is checked in: ``scene`` (a name, path or `Scene`, which must list
    it), else the small retrieval scene with the effect, what it needs, gravity and the rigid
    body; ValueError when the effect has required keys and no scene is given."""
    from reelbench.models import EFFECTS, load_scene
    from reelbench.models.effects import get_effect

    effect = get_effect(name)
    if scene is not None:
        loaded = load_scene(scene, **(overrides or {})) if not hasattr(scene, "effects") else scene.with_(**(overrides or {}))
        if name not in loaded.effects:
            raise ValueError(f"scene {loaded.name!r} does not list effect {name!r} in 'effects': give a scene that does")
        return loaded
    # with gravity and a rigid body, so that the effect acts on a moving, loaded string
    wanted, todo = set(), [name, "gravity", "rigid_body"] + [n for n, e in EFFECTS.items() if e.required]
    while todo:
        n = todo.pop()
        if n not in wanted:
            wanted.add(n)
            todo.extend(get_effect(n).needs)
    effects = [n for n in EFFECTS if n in wanted]
    needed = [f"{s}.{k}" if s else k for s, sec in effect.keys.items() for k, spec in sec.items()
              if name in (spec.required_by or ()) and spec.default is None]
    extra = dict(overrides or {})
    if "axial_damping" in effects and "axial_damping" not in extra:
        extra["axial_damping"] = 0.3
    missing = [k for k in needed if k not in extra and k.split(".")[-1] not in extra]
    if missing:
        raise ValueError(f"effect {name!r} needs values for {', '.join(missing)}: give --scenes FILE (a scene that "
                         "lists it) or --set KEY=VALUE for each")
    return small_scene(effects, **extra)


def check_effect(effect, *, scene=None, overrides: dict | None = None, log: Callable[[str], None] | None = None,
                 raise_on_failure: bool = True, seed: int = 0) -> list[Check]:
    """Check an effect (a registered name, or an `Effect` instance, registered for the checks
    if it is not) against the contract, in ``scene`` (`effect_scene`); returns the checks and
    raises `ContractError` if one fails (unless ``raise_on_failure`` is False)."""
    from reelbench.models.effects import EFFECTS, Effect, register_effect, unregister_effect

    temporary = None
    if isinstance(effect, Effect):
        if EFFECTS.get(effect.name) is None:
            temporary = register_effect(effect).name
        name = effect.name
    elif isinstance(effect, type) and issubclass(effect, Effect):
        return check_effect(effect(), scene=scene, overrides=overrides, log=log, raise_on_failure=raise_on_failure,
                            seed=seed)
    else:
        name = effect
    try:
        sc = effect_scene(name, scene, overrides)
        checks = _run_checks(_effect_checks(name, sc, np.random.default_rng(seed)), log)
    finally:
        if temporary:
            unregister_effect(temporary)
    if raise_on_failure and not all(c.ok for c in checks):
        raise ContractError(f"effect {name!r}", checks)
    return checks


def _effect_checks(name: str, scene, rng) -> list[tuple[str, Callable]]:
    from reelbench.models import build_model

    model = build_model(scene)
    steps = [("declarations", lambda: _effect_declarations(name, model))]
    for term in [t for t in model.terms_of(name) if t in model.potential_terms]:
        steps.append((f"gradient {term}", functools.partial(_gradient, model, term, rng)))
    steps += [("power", lambda: _power(name, model, rng)),
              ("energy balance", lambda: _energy_balance(name, scene, model)),
              ("scene keys", lambda: _scene_keys(name, scene))]
    return steps


def _forces_of(name: str, model):
    own = set(model.terms_of(name))
    return ([model.reel_forces[k] for k in sorted(own & set(model.reel_forces))],
            [model.string_forces[k] for k in sorted(own & set(model.string_forces))])


def _body_loads_of(name: str, model):
    own = set(model.terms_of(name))
    return [model.body_loads[k] for k in sorted(own & set(model.body_loads))]


def _effect_declarations(name: str, model) -> Check:
    from reelbench.models import EFFECTS

    effect = EFFECTS[name]
    reel, string = _forces_of(name, model)
    body = _body_loads_of(name, model)
    problems = [f"needs {n!r}, which is not registered" for n in effect.needs if n not in EFFECTS]
    if (reel or string or body) and not effect.forcing:
        problems.append("has forces but forcing = False: their work W would not be carried")
    if effect.dissipative and not effect.forcing:
        problems.append("dissipative = True without forcing")
    terms = model.terms_of(name)
    return Check("declarations", not problems, "; ".join(problems) if problems else
                 f"terms {', '.join(terms) or 'none'} in scene {model.scene.name!r}; forcing {effect.forcing}, "
                 f"dissipative {effect.dissipative}, needs {', '.join(effect.needs) or 'nothing'}")


def _random_state(model, rng, scale: float = 0.2):
    """A random (x, R, w) near the initial state, with a random attitude."""
    from reelbench.models._jax import jnp
    from reelbench.models.model import quat_to_rot

    x, R, w = model.initial_state()
    x = x + scale * rng.standard_normal(np.shape(x))
    w = w + rng.standard_normal(np.shape(w))
    q = rng.standard_normal(4)
    R = np.asarray(quat_to_rot(q / np.linalg.norm(q))) if model.layout.has_attitude else np.eye(3)
    return jnp.asarray(x), jnp.asarray(R), jnp.asarray(w)


def _gradient(model, term: str, rng, n: int = 3) -> Check:
    from reelbench.models._jax import jax, jnp
    from reelbench.models.model import hat

    V, dV = model.potential_terms[term], model.potential_gradients[term]
    worst = 0.0
    for _ in range(n):
        x, R, w = _random_state(model, rng)
        auto = jax.grad(V, argnums=0)(x, R)
        if model.layout.has_attitude:  # the Ω slot: the derivative along R(I + η^)
            auto = jnp.concatenate([auto, jax.grad(lambda e: V(x, R @ (jnp.eye(3) + hat(e))))(jnp.zeros(3))])
        closed = jnp.asarray(dV(x, R))
        if closed.shape != (model.layout.nw,):
            return Check(f"gradient {term}", False, f"shape {closed.shape}, expected ({model.layout.nw},) "
                                                    "(w's layout: model.over_w)")
        scale = 1.0 + float(jnp.abs(auto).max())
        worst = max(worst, float(jnp.abs(closed - auto).max()) / scale)
    return Check(f"gradient {term}", worst < 1e-10, f"largest |closed form − autodiff| / (1 + |∇V|) = {worst:.2g} "
                                                    f"over {n} random states")


def _power(name: str, model, rng, n: int = 3) -> Check:
    from reelbench.models import EFFECTS

    effect = EFFECTS[name]
    reel, string = _forces_of(name, model)
    body = _body_loads_of(name, model)
    if not reel and not string and not body:
        x, R, w = _random_state(model, rng)
        claimed = effect.power(model, 0.0, x, w)
        claimed_body = effect.body_power(model, 0.0, x, R, w)
        ok = claimed is None and claimed_body is None
        return Check("power", ok, "no forces, no power claimed" if ok else
                     f"claims power {float(claimed if claimed is not None else claimed_body):g} W without forces")
    worst = worst_body = 0.0
    most, on_omega = -np.inf, 0.0
    omega_power = []  # Ω·M of the body loads' moments, where they have one
    for _ in range(n):
        x, R, w = _random_state(model, rng)
        t = float(rng.uniform(0, 2))
        P = sum(float(f(t, x, w)) * float(w[0]) for f in reel) + sum(float(f(t, x, w) @ w) for f in string)
        if reel or string:
            claimed = effect.power(model, t, x, w)
            if claimed is None:
                return Check("power", False, "has forces but power() returns None: give Q·w in closed form")
            worst = max(worst, abs(P - float(claimed)) / (1e-12 + abs(P)))
        if body:
            Qb = [np.asarray(f(t, x, R, w)) for f in body]
            if any(q.shape != (model.layout.nw,) for q in Qb):
                return Check("power", False, f"a body load has shape {[q.shape for q in Qb]}, expected "
                                             f"({model.layout.nw},) (w's layout: model.over_w(dq=..., deta=M))")
            Pb = sum(float(q @ np.asarray(w)) for q in Qb)
            claimed_b = effect.body_power(model, t, x, R, w)
            if claimed_b is None:
                return Check("power", False, "has body loads but body_power() returns None: give Q·w (Ω·M "
                                             "included) in closed form")
            worst_body = max(worst_body, abs(Pb - float(claimed_b)) / (1e-12 + abs(Pb)))
            if model.layout.has_attitude:
                M = sum(q[model.layout.omega] for q in Qb)
                if np.any(M != 0.0):
                    omega_power.append(float(M @ np.asarray(w)[model.layout.omega]))
            P += Pb
        most = max(most, P)
        for f in string:
            if model.layout.has_attitude:
                on_omega = max(on_omega, float(np.abs(np.asarray(f(t, x, w))[model.layout.omega]).max()))
    problems = []
    if worst > 1e-10:
        problems.append(f"claimed power differs from Q·w by {worst:.2g} (relative)")
    if worst_body > 1e-10:
        problems.append(f"claimed body power differs from Q·w (Ω·M included) by {worst_body:.2g} (relative)")
    if effect.dissipative and most > 1e-14:
        problems.append(f"dissipative, yet Q·w = {most:.3g} W > 0")
    if on_omega:
        problems.append(f"a string force acts on Ω ({on_omega:.3g})")
    return Check("power", not problems, "; ".join(problems) if problems else
                 f"Q·w = claimed power to {max(worst, worst_body):.2g} (relative) over {n} random states"
                 + (f" (body loads' Ω·M {', '.join(f'{p:.3g}' for p in omega_power)} W included)" if omega_power
                    else "")
                 + (f"; largest {most:.3g} W ≤ 0 (dissipative)" if effect.dissipative else ""))


def _energy_balance(name: str, scene, model, t_end: float = 0.5) -> Check:
    """DOP853 on the closed-form equations (the ones every integrator but the autodiff path
    reads): E − W must hold still, which it does only if gradient, force and work agree."""
    from scipy.integrate import solve_ivp

    from reelbench.integrators import Trajectory
    from reelbench.integrators.rhs import rhs_jit
    from reelbench.models.diagnostics import evaluate, summary

    lay, f = model.layout, rhs_jit(model)
    t_end = min(t_end, scene.t_end)
    t_eval = np.linspace(0.0, t_end, 26)
    sol = solve_ivp(lambda t, y: np.asarray(f(t, y)), (0.0, t_end), np.asarray(model.initial_ode_state()),
                    t_eval=t_eval, **VERIFY_BALANCE_REFERENCE)
    if sol.status != 0:
        return Check("energy balance", False, f"the reference failed: {sol.message}")
    y = sol.y.T
    traj = Trajectory(t=sol.t, x=y[:, lay.y_x], attitude=y[:, lay.y_quat] if lay.has_attitude else None,
                      attitude_kind="quaternion", velocity=y[:, lay.y_w],
                      work=y[:, lay.y_work][:, 0] if lay.has_work else np.zeros(len(sol.t)))
    err = summary(evaluate(scene, traj), has_work=lay.has_work)["energy_error"]
    what = "E − W" if lay.has_work else "E"
    return Check("energy balance", bool(err < ENERGY_TOLERANCE),
                 f"max |Δ({what})| / max T = {err:.2g} over {t_end:g} s by DOP853 (rtol {VERIFY_BALANCE_REFERENCE['rtol']:g}), "
                 f"allowed {ENERGY_TOLERANCE:g}; W at the end {traj.work[-1]:.3g} J")


_BREAKS = {  # a value that breaks each rule of a key kind, and one of the wrong type
    ("float", "positive"): -1.0, ("float", "nonnegative"): -1.0, ("float", "finite"): float("inf"),
    ("float", "stretch"): -1.0, ("int", "at_least_1"): 0, ("int", "finite"): 1.5,
    ("vec3", "positive"): [1.0, -1.0, 1.0], ("vec3", "nonzero"): [0.0, 0.0, 0.0], ("vec3", "finite"): [1.0, 2.0],
    ("mat3", "spd"): [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
    ("mat3", "rotation"): [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    ("str", "finite"): 1.0, ("str", "line"): "two\nlines", ("str", "name"): "../x",
}


#: a value of each kind other than the usual defaults (a key at its default is allowed without its effect)
_OTHER = {"float": 0.5, "int": 2, "vec3": [0.1, 0.2, 0.3], "mat3": [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.0]],
          "str": "other"}


def _scene_keys(name: str, scene) -> Check:
    """Each key the effect owns, broken three ways, must be refused by a SceneError naming it."""
    from reelbench.models import EFFECTS, SceneError, scene_from_dict

    effect = EFFECTS[name]
    base = scene.to_dict()
    tried, unnamed = 0, []

    def refused(d, dotted, how) -> None:
        nonlocal tried
        tried += 1
        try:
            scene_from_dict(d, source="verify.toml")
        except SceneError as exc:
            if f"'{dotted}'" not in str(exc) and dotted not in str(exc):
                unnamed.append(f"{how}: {str(exc)[:160]}")
            return
        unnamed.append(f"{how}: accepted")

    for section, keys in effect.keys.items():
        for key, spec in keys.items():
            dotted = f"{section}.{key}" if section else key
            table = base.get(section, {}) if section else base
            if key not in table and spec.default is None:
                continue
            def changed(value, drop=False):
                d = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
                tgt = d.setdefault(section, {}) if section else d
                if drop:
                    tgt.pop(key, None)
                else:
                    tgt[key] = value
                return d
            bad = _BREAKS.get((spec.kind, spec.rule), "not a value" if spec.kind != "str" else 1.0)
            refused(changed(bad), dotted, f"{dotted} = {bad!r}")
            refused(changed("text" if spec.kind != "str" else 1.0), dotted, f"{dotted} of the wrong type")
            if name in (spec.required_by or ()) and spec.default is None:
                refused(changed(None, drop=True), dotted, f"{dotted} missing")
            if spec.only_with_effect:  # the effect removed, with all its keys but this one
                value = table.get(key, spec.default)
                if value == spec.default or (spec.kind in ("vec3", "mat3") and value is not None
                                             and np.array_equal(value, spec.default)):
                    # its default is accepted without the effect: give a value other than it
                    value = _OTHER.get(spec.kind, value)
                d = changed(value)
                # and with the effects that need it (drag needs buoyancy), and their keys: else the
                # scene is refused for the effect they miss, not for this key
                gone = {name}
                while True:
                    more = {e for e in d["effects"] if e not in gone and set(EFFECTS[e].needs) & gone}
                    if not more:
                        break
                    gone |= more
                d["effects"] = [e for e in d["effects"] if e not in gone]
                for sec, others in [kv for g in gone for kv in EFFECTS[g].keys.items()]:
                    tgt = d.get(sec, {}) if sec else d
                    for other in others:
                        if (sec, other) != (section, key) and isinstance(tgt, dict):
                            tgt.pop(other, None)
                refused(d, dotted, f"{dotted} without the effect"
                        + (f" (nor {', '.join(sorted(gone - {name}))}, which need it)" if len(gone) > 1 else ""))
    if not tried:
        return Check("scene keys", True, "owns no scene keys")
    return Check("scene keys", not unnamed, f"{tried - len(unnamed)} of {tried} broken values refused naming their key"
                 + ("" if not unnamed else ": " + "; ".join(unnamed[:3])))


# ------------------------------------------------------------------------------------------
# The command
# ------------------------------------------------------------------------------------------
def kind_of(name: str) -> str:
    """"integrator" or "effect" for a registered name; ValueError naming both registries otherwise."""
    from reelbench.integrators import available
    from reelbench.models.effects import EFFECTS, ensure_known

    if name in available():
        return "integrator"
    ensure_known([name])
    if name in EFFECTS:
        return "effect"
    raise ValueError(f"verify: {name!r} is neither a registered integrator ({', '.join(available())}) nor an effect "
                     f"({', '.join(EFFECTS)}); install the plugin first (see `python -m benchmark list`)")


def verify(name: str, *, scene=None, overrides: dict | None = None, log: Callable[[str], None] = print) -> int:
    """``python -m benchmark verify NAME``: one line per check, then a summary; exit status 0
    when every check holds, 1 otherwise."""
    import time

    t0 = time.perf_counter()
    kind = kind_of(name)
    log(f"verify {kind} {name!r}:")
    if kind == "integrator":
        checks = check_integrator(name, log=log, raise_on_failure=False)
    else:
        checks = check_effect(name, scene=scene, overrides=overrides, log=log, raise_on_failure=False)
    failed = [c.name for c in checks if not c.ok]
    log(f"{len(checks) - len(failed)} of {len(checks)} checks hold ({time.perf_counter() - t0:.0f} s)"
        + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0
