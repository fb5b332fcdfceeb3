"""Test helpers shared by several test files (not a test module)."""

import itertools

import numpy as np
from scipy.integrate import solve_ivp

from reelbench.integrators.base import Trajectory
from reelbench.models import build_model, load_scene


#: The fluid's keys of the water scenes (drag and buoyancy), as `scene_with_effects` adds them
WATER = {"fluid.density": 1025.0, "string.diameter": 0.007, "normal_drag": 1.3, "tangential_drag": 0.02,
         "body.volume": 2e-4}
#: a fluid test scene's body drag (with a rigid body at zero offset: the drag acts at its centre of mass)
BODY_DRAG_AREA = 0.05


def fluid_combinations():
    """Effect lists with the fluid effects: buoyancy alone, and drag at a fixed length and with a reel,
    each with a point mass and a rigid body."""
    out = []
    for body in ([], ["rigid_body"]):
        out.append(["elasticity", "gravity", *body, "buoyancy"])
        out.append(["elasticity", "gravity", *body, "buoyancy", "drag"])
        out.append(["elasticity", "gravity", *body, "reel", "carnot", "reel_control", "buoyancy", "drag"])
    return out


def effect_combinations():
    """Every valid effect list (elasticity always present)."""
    out = []
    for gravity, body, reel in itertools.product([False, True], repeat=3):
        base = ["elasticity"] + (["gravity"] if gravity else []) + (["rigid_body"] if body else [])
        if not reel:
            out.append(base)
            continue
        for carnot, control in itertools.product([False, True], repeat=2):
            out.append(base + ["reel"] + (["carnot"] if carnot else []) + (["reel_control"] if control else []))
    return out


def scene_with_effects(effects, elements=3, **overrides):
    """The retrieval scene reduced to ``effects`` (values adjusted to stay valid)."""
    kw = dict(effects=effects, elements=elements, tip_velocity=[0.3, 1.0, -0.2], reel_rate=0.0)
    if "rigid_body" not in effects:
        kw["angular_velocity"] = [0.0, 0.0, 0.0]
    else:
        kw["angular_velocity"] = [0.4, -0.3, 0.8]
    if "reel_control" not in effects:
        kw["control_moment"] = 0.0
    if "reel" in effects:
        kw["reel_rate"] = -0.7
    if "buoyancy" in effects:
        kw.update({k: v for k, v in WATER.items() if k != "normal_drag" and k != "tangential_drag"})
    if "drag" in effects:
        kw.update(normal_drag=WATER["normal_drag"], tangential_drag=WATER["tangential_drag"],
                  **{"body.drag_area": BODY_DRAG_AREA, "fluid.current": [0.3, -0.2, 0.1]})
        if "rigid_body" in effects:
            kw["attachment_to_com"] = [0.0, 0.0, 0.0]
    kw.update(overrides)
    return load_scene("retrieval", **kw)


def random_state(model, rng, scale=0.2):
    """A random (x, R, w) near the initial state, with a random attitude."""
    x, R, w = model.initial_state()
    x = x + scale * rng.standard_normal(x.shape)
    w = w + rng.standard_normal(w.shape)
    quat = rng.standard_normal(4)
    quat /= np.linalg.norm(quat)
    from reelbench.models.model import quat_to_rot

    R = np.asarray(quat_to_rot(quat)) if model.layout.has_attitude else np.eye(3)
    return x, R, w


def reference_solution(scene, t_end, rtol=1e-11, atol=1e-12, n_save=21, method="DOP853"):
    """scipy solve_ivp straight on the model's ODE (independent of the integrator plugins)."""
    model = build_model(scene)
    f = model.ode_rhs_jit
    lay = model.layout
    t_eval = np.linspace(0.0, t_end, n_save)
    sol = solve_ivp(lambda t, y: np.asarray(f(t, y)), (0.0, t_end), model.initial_ode_state(),
                    method=method, rtol=rtol, atol=atol, t_eval=t_eval)
    assert sol.status == 0, sol.message
    y = sol.y.T
    return Trajectory(
        t=sol.t, x=y[:, lay.y_x], attitude=y[:, lay.y_quat] if lay.has_attitude else None,
        attitude_kind="quaternion", velocity=y[:, lay.y_w],
        work=y[:, lay.y_work][:, 0] if lay.has_work else np.zeros(len(sol.t)),
        stats={"rhs_evals": sol.nfev}, integrator="solve_ivp-" + method,
    )


def installed_plugin(site, module: str, code: str, entry: str, group: str = "reelbench.integrators"):
    """Write ``code`` as ``module``.py into the directory ``site`` with the metadata of an
    installed distribution declaring ``entry`` ("name = module:Class") in entry-point ``group``,
    so that a process with ``site`` on its path finds it as a plugin. Returns ``site``."""
    site.mkdir(parents=True, exist_ok=True)
    (site / f"{module}.py").write_text(code)
    dist = site / f"{module}-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module.replace('_', '-')}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{group}]\n{entry}\n")
    return site
