"""The plugin contract of an effect, checked (`check_effect`; the command is
`benchmark.contract.verify`).

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
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np

from reelbench.benchmark.contract.checks import Check, ContractError, run_checks, small_scene
from reelbench.benchmark.core.policy import VERIFY_BALANCE_REFERENCE

#: |E − W − E0| / max T allowed of the reference on an effect's scene
ENERGY_TOLERANCE = 1e-7


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
        checks = run_checks(_effect_checks(name, sc, np.random.default_rng(seed)), log)
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
