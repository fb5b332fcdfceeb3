"""Diagnostics of a trajectory, from any integrator's state (models/README.md, "What is reported").

    df = evaluate(scene, trajectory)   # pandas.DataFrame, one row per saved time

Attitude may be rotation matrices or (not renormalised) quaternions; the state may carry
velocities or momenta (then the continuous Legendre transform recovers velocities).

Columns: t, energy, kinetic, T_rot, V_gravity, V_elastic, V_reel, work, energy_minus_work,
power (Q·w of the non-conservative forces), work_path (its integral along the saved times; the
work of a trajectory that carries none), pi3, orthogonality_error, deployed_length, stretched_length, reel_rate, omega_1..3,
body_x..z (the attachment point r_p + q_{N+1}), tension_min, tension_max.
``energy`` holds only the terms of the scene's effects; ``V_gravity`` is the sum of the terms
the `gravity` effect contributes (`StringPendulum.terms_of`); ``V_reel`` is one of them (the
reel-side string) and is reported separately for reel scenes. Every other effect with
potential terms (buoyancy, a plugin's spring) has its own column ``V_<effect>``, the sum of its
terms (`effect_energy_columns`), so that T + V_gravity + V_elastic + the ``V_<effect>`` columns
add up to ``energy``.
"""

from __future__ import annotations

import functools

import numpy as np
import pandas as pd

from reelbench.models._jax import jax, jnp
from reelbench.models.model import StringPendulum, build_model, quat_to_rot

E3 = jnp.array([0.0, 0.0, 1.0])


#: effects whose potential terms have columns of their own (V_gravity, V_elastic)
_NAMED_ENERGY = ("gravity", "elasticity")


def effect_energy_columns(model: StringPendulum) -> tuple[str, ...]:
    """``V_<effect>`` of every listed effect but gravity and elasticity that has potential terms
    (buoyancy, a plugin's potential), in the model's order."""
    owners = [model.term_owner[k] for k in model.potential_terms]
    return tuple(f"V_{e}" for e in dict.fromkeys(owners) if e not in _NAMED_ENERGY)


def point_diagnostics(model: StringPendulum, x, R, w, W, t=0.0) -> dict:
    """All scalar diagnostics at one state (x, R, w) at time t with accumulated work W."""
    lay = model.layout
    kin = {k: f(x, R, w) for k, f in model.kinetic_terms.items()}
    pot = {k: f(x, R) for k, f in model.potential_terms.items()}
    T = sum(kin.values())
    V = sum(pot.values(), jnp.asarray(0.0))
    om = model.omega(w)
    p = model.momentum(x, R, w)
    q = model.nodes(x)
    pq = jnp.concatenate([jnp.zeros((1, 3)), p[lay.nodes].reshape(model.N, 3)], axis=0)
    ang = jnp.sum(jnp.cross(q, pq), axis=0)
    if lay.has_attitude:
        ang = ang + R @ p[lay.omega]
    _, stretch, _ = model.elements(x)
    tension = model.tensions(x)
    # gravity's own terms (string, body and, with a reel, the reel-side string), whatever they are named
    v_gravity = sum((pot[k] for k in model.terms_of("gravity")), 0.0)
    body = model.r_p + q[-1]
    # every other effect's potential terms, by effect (the parts then add up to E)
    effect_energy = {c: jnp.asarray(sum(pot[k] for k in model.terms_of(c[2:]) if k in pot))
                     for c in effect_energy_columns(model)}
    return {
        **effect_energy,
        "energy": T + V,
        "kinetic": T,
        "T_rot": 0.5 * om @ (model.J_c @ om) if lay.has_attitude else jnp.asarray(0.0),
        "V_gravity": jnp.asarray(v_gravity),
        "V_elastic": pot["V_elastic"],
        "V_reel": jnp.asarray(pot.get("V_reel", 0.0)),
        "work": W,
        "energy_minus_work": T + V - W,
        # Q·w of the non-conservative forces: `evaluate` integrates it along the saved path
        "power": model.power(t, x, w, R) if lay.has_work else jnp.asarray(0.0),
        "pi3": ang[2],
        "orthogonality_error": jnp.linalg.norm(jnp.eye(3) - R.T @ R) if lay.has_attitude else jnp.asarray(0.0),
        "deployed_length": model.L - model.reel_coordinate(x),
        "stretched_length": jnp.sum(stretch),
        "reel_rate": model.reel_rate(w),
        "omega_1": om[0],
        "omega_2": om[1],
        "omega_3": om[2],
        "body_x": body[0],
        "body_y": body[1],
        "body_z": body[2],
        "tension_min": jnp.min(tension),
        "tension_max": jnp.max(tension),
    }


@functools.lru_cache(maxsize=64)
def _batched(model: StringPendulum, attitude_kind: str, from_momentum: bool):
    def one(t, x, att, v, W):
        if not model.layout.has_attitude:
            R = jnp.eye(3)
        elif attitude_kind == "quaternion":
            R = quat_to_rot(att)
        else:
            R = att
        w = model.velocity_from_momentum(x, R, v) if from_momentum else v
        return point_diagnostics(model, x, R, w, W, t)

    return jax.jit(jax.vmap(one))


def evaluate(scene, trajectory) -> pd.DataFrame:
    """Diagnostics of ``trajectory`` (any integrator's `Trajectory`) for ``scene``."""
    model = build_model(scene)
    tr = trajectory
    n = len(tr.t)
    columns = ["t"] + list(_COLUMNS) + list(effect_energy_columns(model)) + ["work_path"]
    if n == 0:
        return pd.DataFrame(columns=columns)
    from_momentum = tr.velocity is None
    v = tr.momentum if from_momentum else tr.velocity
    if v is None:
        raise ValueError("trajectory carries neither velocity nor momentum")
    att = tr.attitude if (model.layout.has_attitude and tr.attitude is not None) else np.zeros((n, 3, 3))
    kind = tr.attitude_kind if model.layout.has_attitude else "matrix"
    work = tr.work if tr.work is not None else np.zeros(n)
    out = _batched(model, kind, from_momentum)(
        jnp.asarray(tr.t, dtype=float), jnp.asarray(tr.x), jnp.asarray(att), jnp.asarray(v), jnp.asarray(work, dtype=float)
    )
    data = {"t": np.asarray(tr.t, dtype=float)}
    data.update({k: np.asarray(out[k], dtype=float) for k in _COLUMNS})
    data.update({k: np.asarray(out[k], dtype=float) for k in effect_energy_columns(model)})
    # the work of the scene's forces along the saved path (trapezoidal rule over the saved
    # times): the balance of a trajectory that carries no work of its own (a method that does
    # not know the scene's forces) is taken with it, so ignoring a force shows as an imbalance
    t = data["t"]
    data["work_path"] = np.concatenate([[0.0], np.cumsum(0.5 * np.diff(t) * (data["power"][1:] + data["power"][:-1]))])
    if tr.work is None and model.layout.has_work:
        data["work"] = data["work_path"]
        data["energy_minus_work"] = data["energy"] - data["work_path"]
    if model.layout.has_attitude and kind == "quaternion":
        data["quaternion_norm_error"] = np.abs(np.linalg.norm(np.asarray(tr.attitude), axis=1) - 1.0)
    return pd.DataFrame(data)


_COLUMNS = (
    "energy", "kinetic", "T_rot", "V_gravity", "V_elastic", "V_reel", "work", "energy_minus_work", "power", "pi3",
    "orthogonality_error", "deployed_length", "stretched_length", "reel_rate", "omega_1", "omega_2",
    "omega_3", "body_x", "body_y", "body_z", "tension_min", "tension_max",
)


def energy_deviation(df: pd.DataFrame, *, has_work: bool) -> pd.Series:
    """|E - E0| / max T per saved time, or |(E - W) - (E0 - W0)| / max T with forcing (the paper's metric)."""
    e = df["energy_minus_work"] if has_work else df["energy"]
    tmax = float(df["kinetic"].max())
    return np.abs(e - e.iloc[0]) / tmax if tmax > 0 else e * np.nan


def summary(df: pd.DataFrame, *, has_work: bool) -> dict:
    """The paper's conservation metrics of one run (models/README.md, "What is reported").

    ``df``: `evaluate`'s table of the run; ``has_work`` (keyword only): whether the scene does
    non-conservative work (``build_model(scene).layout.has_work``), which makes the energy error
    that of E − W. Returns {"energy_error", "pi3_error", "orthogonality_error"} (floats; NaN
    for an empty table).

    energy_error: max |E - E0| / max T   (or max |(E - W) - (E0 - W0)| / max T with forcing)
    pi3_error: max |π3 - π3(0)| / |π3(0)|  (absolute if π3(0) = 0)
    orthogonality_error: max ‖I - RᵀR‖
    """
    if len(df) == 0:
        return {"energy_error": np.nan, "pi3_error": np.nan, "orthogonality_error": np.nan}
    pi0 = float(df["pi3"].iloc[0])
    dpi = float(np.max(np.abs(df["pi3"] - pi0)))
    return {
        "energy_error": float(energy_deviation(df, has_work=has_work).max()),
        "pi3_error": dpi / abs(pi0) if abs(pi0) > 1e-12 else dpi,
        "orthogonality_error": float(df["orthogonality_error"].max()),
    }
