"""What the cross-validation (`benchmark.studies.xval`) can give the outside codes, and what every
code's run returns.

The same fixed-length string is built in MoorDyn (`benchmark.studies.xval_moordyn`) and MuJoCo
(`benchmark.studies.xval_mujoco`) from one of our scenes: `check_translatable` refuses what they
cannot represent (`Untranslatable`, naming it), `time_step` is their fixed step, `initial_nodes`
our initial state as they take it, and `CodeRun` the tip positions and cost of one run of any code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from reelbench.models.scene import Scene

#: Effects the translation understands (everything else is refused); the fluid's only MoorDyn's.
SUPPORTED_EFFECTS = ("gravity", "elasticity", "rigid_body", "buoyancy", "drag")
FLUID_EFFECTS = ("buoyancy", "drag")
#: The water of the ``in_water`` case (MoorDyn's line of the point-mass case, placed in sea
#: water): normal and tangential drag coefficients, a string that sinks, a dense body with a
#: drag area. A scene with its own fluid effects keeps its values.
WATER = {"fluid.density": 1025.0, "string.diameter": 0.007, "normal_drag": 1.3, "tangential_drag": 0.02,
         "body.volume": 1.25e-4, "body.drag_area": 0.02}
#: Fixed time step of MoorDyn / MuJoCo: dt = min(DT_MAX, CFL / ω_max) with ω_max = (2/l)·√(EA/μ)
#: the highest frequency of the lumped chain (RK4: stable up to 2.8; its error ∝ dt⁴). 0.025 keeps
#: their time error below `benchmark.studies.xval.MODEL_TOLERANCE` over the default 5 s at every N
#: of the study (measured by rerunning at dt/2: at most 1.8e-10 m, in water at N = 5, where dt is
#: largest; 0.05 gave 3.2e-9 m there).
CFL = 0.025
DT_MAX = 1e-3


class Untranslatable(ValueError):
    """The scene has something the outside codes cannot represent; the message names it."""


# ------------------------------------------------------------------------------------------
# What can be translated
# ------------------------------------------------------------------------------------------
def check_translatable(scene: Scene, code: str) -> None:
    """Raise `Untranslatable` naming every part of ``scene`` that ``code`` ("moordyn" or
    "mujoco") cannot represent."""
    if code not in ("moordyn", "mujoco"):
        raise ValueError(f"code must be 'moordyn' or 'mujoco', not {code!r}")
    why = []
    for e in scene.effects:
        if e == "slack" and code == "moordyn":  # MoorDyn's lines are tension-only: the same law
            continue
        if e not in SUPPORTED_EFFECTS:
            what = {"reel": "a reel (effect 'reel': the deployed length changes)",
                    "carnot": "effect 'carnot' (needs a reel)", "reel_control": "effect 'reel_control' (needs a reel)",
                    "slack": "effect 'slack' (tension-only elasticity: MuJoCo's tendon springs are two-sided)",
                    "axial_damping": "effect 'axial_damping' (string damping)"}.get(e, f"effect {e!r}")
            why.append(what)
    if scene.initial.stretch < 1.0:
        why.append(f"initial.stretch = {scene.initial.stretch:g} < 1 (a compressed start: MoorDyn's lines carry no "
                   "compression)")
    if code == "moordyn" and scene.has("rigid_body"):
        why.append("effect 'rigid_body' (MoorDyn is given point masses only; the body runs are against MuJoCo)")
    if code == "mujoco":
        why += [f"effect {e!r} (MuJoCo's fluid model is not Morison's: the fluid cases are against MoorDyn)"
                for e in FLUID_EFFECTS if scene.has(e)]
    if code == "moordyn" and scene.has("drag") and any(scene.section("fluid")["current"]):
        why.append("a current (fluid.current: MoorDyn reads currents from its wave-kinematics input, not translated)")
    if why:
        raise Untranslatable(f"{code} cannot translate scene {scene.name!r}: " + "; ".join(why)
                             + ": give a fixed-length scene without those effects (e.g. --scenes fixed_length)")


def time_step(scene: Scene) -> float:
    """The fixed step used for MoorDyn and MuJoCo at this scene's N (see `CFL`)."""
    st = scene.string
    l = scene.initial.deployed_length / st.elements
    omega = 2.0 / l * math.sqrt(st.axial_stiffness / st.mass_per_length)
    return min(DT_MAX, CFL / omega)


class InitialNodes(NamedTuple):
    """Our initial state as the outside codes take it (our frame): absolute node positions and
    velocities (N+1, 3), the body's attitude and angular velocity."""

    q: np.ndarray
    v: np.ndarray
    R: np.ndarray
    omega: np.ndarray


def initial_nodes(scene: Scene) -> InitialNodes:
    """Our initial state (straight, unstretched, linear velocity profile) as the outside codes take it."""
    from reelbench.models import build_model

    model = build_model(scene)
    x, R, w = model.initial_state()
    N, lay = model.N, model.layout
    q = np.vstack([np.zeros(3), np.asarray(x[lay.nodes]).reshape(N, 3)]) + model.r_p
    v = np.vstack([np.zeros(3), np.asarray(w[lay.nodes]).reshape(N, 3)])
    return InitialNodes(q, v, np.asarray(R), np.asarray(model.omega(w)))


@dataclass
class CodeRun:
    """Attachment-point (tip) positions of one code at the output times, and its cost."""

    code: str
    N: int
    dt: float | None
    tip: np.ndarray  # (n_t, 3), our frame, absolute
    steps: int
    wall_s: float
    extra: dict = field(default_factory=dict)

    @property
    def us_per_step(self) -> float:
        """Median over output intervals when they were timed one by one (robust to load spikes
        and first-call set-up), else the whole run's mean; a run read back from the study's table
        (``extra["us_per_step"]``) as the table states it."""
        if "us_per_step" in self.extra:
            return self.extra["us_per_step"]
        if "interval_s" in self.extra:
            return 1e6 * float(np.median(self.extra["interval_s"])) / self.extra["steps_per_interval"]
        return 1e6 * self.wall_s / self.steps if self.steps else float("nan")


def steps_per_interval(times, dt) -> int:
    """The steps of ``dt`` in one interval of ``times`` (evenly spaced, multiples of dt), or ValueError."""
    dt_out = times[1] - times[0]
    n = round(dt_out / dt)
    if n < 1 or abs(n * dt - dt_out) > 1e-9 * dt_out or not np.allclose(np.diff(times), dt_out, rtol=1e-12, atol=1e-12):
        raise ValueError(f"output times must be evenly spaced multiples of dt = {dt:g} s (got spacing {dt_out:g} s)")
    return n


