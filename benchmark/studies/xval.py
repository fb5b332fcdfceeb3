"""Cross-validation against MoorDyn and MuJoCo (``python -m benchmark xval``).

The same fixed-length string is built in three codes from one scene:

* **ours**: `models` with ``string.mass_model`` "consistent" (the paper's) and "lumped"
  (models/README.md). The study integrates both with our LGVI at the outside codes' step /
  `OURS_REFINE` (`run_ours_lgvi`: the cost table, the self-convergence and the Richardson
  limits), and the lumped one also with the benchmark's reference solver (`run_ours`:
  `benchmark.core.reference`, DOP853 at rtol 1e-12 / atol 1e-14 on the closed-form right-hand side):
  that solution, whose time error is far below `MODEL_TOLERANCE`, is the one compared with the
  outside codes at equal N (the LGVI's time error, up to 1.4e-6 m at N = 5 over 5 s, would hide
  the model difference);
* **MoorDyn** (point mass only): one line from a fixed point at r_p to a free point of mass
  m_b, in vacuum fluid density 0 and every hydrodynamic coefficient 0 (no buoyancy, drag or added
  mass; the ``in_water`` case: `WATER`, without added mass),
  internal damping BA = 0, bending EI = 0, water depth 10 km (no seabed contact), RK4. MoorDyn's
  z points up and ours (e3) down: ours (x, y, z) is MoorDyn's (x, −y, −z) (a rotation by π about
  e1, so handedness is kept). MoorDyn builds its own (catenary) initial line shape even without
  initial-condition solving, so its state is saved, the positions and velocities are overwritten
  with ours (straight, unstretched, linear velocity profile) and the state is loaded back;
  the positions it reports are read only after a step;
* **MuJoCo** (point mass and rigid body): each free node a point body on three slide joints,
  neighbours linked by spatial tendons of stiffness EA/l and spring length l, gravity (0, 0, g)
  in our frame (MuJoCo has no preferred "up"), contacts off, RK4. The rigid body is a body on a
  free joint whose frame origin is the attachment point (the last tendon's site), carrying J_c
  and m_b at ρ_c plus the last node's lumped mass μl/2 at its origin (one combined inertia).

Both outside codes are lumped-mass discretisations, so at equal N they and our lumped model are
the *same* discrete system: the study compares our lumped model's DOP853 solution with each
outside code at its step dt (`CFL`), and reruns each outside code at dt/2 (``<code>_half_dt``) so
that the tables show the outside codes' own time error too; both must be below
`MODEL_TOLERANCE` for the equal-N difference to measure the model and not the time steppers
(tests/test_xval.py checks the difference to 1e-8 m in vacuum and 1e-9 m in water); our consistent
model converges to the same continuum limit. `study` runs every code of every case at every N (one
engine job per (case, N), in this process: the per-step costs are compared); its tables, plots
and README are `benchmark.studies.xval_report`'s. `run_xval`, the command's pipeline, keeps
the runs of an earlier study in its output directory that it does not recompute.

Not translated (refused with `Untranslatable`, naming it): a reel or its effects, `slack` for
MuJoCo (its tendon springs are two-sided; MoorDyn's lines are tension-only, so MoorDyn takes
`slack` as it is, and agrees with the two-sided law only while every element stays stretched,
which `run` checks; tests/test_slack_moordyn.py compares a string that goes slack), `axial_damping`, an
initial compression (`initial.stretch` < 1); MoorDyn is not given the rigid body (its Body model
was not validated here: the body runs are against MuJoCo only).
"""

from __future__ import annotations

import contextlib
import math
import os
import struct
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from reelbench.benchmark.core import engine
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.report import Provenance
from reelbench.benchmark.runs.metrics import body_positions
from reelbench.benchmark.core.reference import CACHE_DIR, get_reference
from reelbench.models.scene import Scene

#: Effects the translation understands (everything else is refused); the fluid's only MoorDyn's.
SUPPORTED_EFFECTS = ("gravity", "elasticity", "rigid_body", "buoyancy", "drag")
FLUID_EFFECTS = ("buoyancy", "drag")
#: The water of the ``in_water`` case (MoorDyn's line of the point-mass case, placed in sea
#: water): normal and tangential drag coefficients, a string that sinks, a dense body with a
#: drag area. A scene with its own fluid effects keeps its values.
WATER = {"fluid.density": 1025.0, "string.diameter": 0.007, "normal_drag": 1.3, "tangential_drag": 0.02,
         "body.volume": 1.25e-4, "body.drag_area": 0.02}
#: Default N sequence and horizon of `python -m benchmark xval`.
DEFAULT_ELEMENTS = (5, 10, 20, 40, 80)  # N = 160 (`--elements 5,10,20,40,80,160`) costs 4x the rest
DEFAULT_T_END = 5.0
#: Fixed time step of MoorDyn / MuJoCo: dt = min(DT_MAX, CFL / ω_max) with ω_max = (2/l)·√(EA/μ)
#: the highest frequency of the lumped chain (RK4: stable up to 2.8; its error ∝ dt⁴). 0.025 keeps
#: their time error below `MODEL_TOLERANCE` over the default 5 s at every N of the study (measured
#: by rerunning at dt/2: at most 1.8e-10 m, in water at N = 5, where dt is largest; 0.05 gave
#: 3.2e-9 m there).
CFL = 0.025
DT_MAX = 1e-3
#: What "the same discrete model" must show at equal N: the largest tip distance between our
#: lumped model (DOP853) and an outside code, and each outside code's own time error (the change
#: when its dt is halved), over the compared horizon.
MODEL_TOLERANCE = 1e-9

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


def _initial_nodes(scene: Scene) -> InitialNodes:
    from reelbench.models import build_model

    model = build_model(scene)
    x, R, w = model.initial_state()
    N, lay = model.N, model.layout
    q = np.vstack([np.zeros(3), np.asarray(x[lay.nodes]).reshape(N, 3)]) + model.r_p
    v = np.vstack([np.zeros(3), np.asarray(w[lay.nodes]).reshape(N, 3)])
    return InitialNodes(q, v, np.asarray(R), np.asarray(model.omega(w)))


# ------------------------------------------------------------------------------------------
# MoorDyn
# ------------------------------------------------------------------------------------------
#: ours (x, y, z), e3 down  <->  MoorDyn (x, −y, −z), z up (rotation by π about e1; its own inverse)
TO_MOORDYN = np.diag([1.0, -1.0, -1.0])
MOORDYN_DEPTH = 1e4  # m: no seabed contact
#: In a fluid, MoorDyn's line is placed this far below its water surface (its z = 0), so that
#: every segment stays wholly submerged (ours are: models/effects.py, Buoyancy); in vacuum 0.
SUBMERGED = 100.0


def _md_offset(scene: Scene) -> np.ndarray:
    """MoorDyn position = TO_MOORDYN @ ours + this (a shift below the surface in a fluid)."""
    return np.array([0.0, 0.0, -SUBMERGED if scene.has("buoyancy") else 0.0])


def moordyn_input(scene: Scene, dt: float) -> str:
    """MoorDyn v2 input file of the scene (point mass, fixed length)."""
    check_translatable(scene, "moordyn")
    st = scene.string
    q = _initial_nodes(scene).q
    a, b = TO_MOORDYN @ q[0] + _md_offset(scene), TO_MOORDYN @ q[-1] + _md_offset(scene)
    f = "{:.17g}".format
    # in vacuum the diameter only sets MoorDyn's volume (buoyancy, drag): irrelevant with fluid density 0
    diameter, cd, cd_axial, density, volume, cda = "0.01", "0.0", "0.0", "0.0", "0.0", "0.0"
    fluid_note = "fluid density: no buoyancy, drag or added mass"
    if scene.has("buoyancy"):  # MoorDyn's Cd, CdAx are our C_n, C_t; added mass (Ca, CaAx) stays 0
        diameter, density, volume = f(scene.string.diameter), f(scene.section("fluid")["density"]), \
            f(scene.section("body")["volume"])
        fluid_note = "fluid density (buoyancy and drag; no added mass: Ca = 0)"
    if scene.has("drag"):
        cd, cd_axial = f(scene.string.normal_drag), f(scene.string.tangential_drag)
        cda = f(scene.section("body")["drag_area"])
    return "\n".join([
        "--------------------- MoorDyn Input File ------------------------------------",
        f"reelbench xval: scene {scene.name} (generated by benchmark/studies/xval.py)",
        "----------------------- LINE TYPES ------------------------------------------",
        "TypeName   Diam    Mass/m     EA     BA/-zeta    EI    Cd     Ca     CdAx    CaAx",
        "(name)     (m)     (kg/m)     (N)    (N-s/-)     (-)   (-)    (-)    (-)     (-)",
        f"string     {diameter}    {f(st.mass_per_length)}    {f(st.axial_stiffness)}    0.0    0.0    {cd}    0.0    {cd_axial}    0.0",
        "---------------------------- POINTS -----------------------------------------",
        "ID    Attachment  X       Y     Z      Mass   Volume  CdA    Ca",
        "(#)   (-)         (m)    (m)   (m)    (kg)   (m^3)   (m^2)  (-)",
        f"1     Fixed       {f(a[0])}    {f(a[1])}    {f(a[2])}    0.0    0.0    0.0    0.0",
        f"2     Free        {f(b[0])}    {f(b[1])}    {f(b[2])}    {f(scene.body.mass)}    {volume}    {cda}    0.0",
        "-------------------------- LINES -------------------------------------------------",
        "ID   LineType   AttachA  AttachB  UnstrLen  NumSegs  LineOutputs",
        "(#)  (name)     (#)      (#)      (m)       (-)      (-)",
        f"1    string     1        2        {f(scene.initial.deployed_length)}    {st.elements}    -",
        "-------------------------- SOLVER OPTIONS ---------------------------------------",
        f"{f(dt)}    dtM       - time step",
        "RK4    tScheme   - 4th order Runge-Kutta",
        f"{f(scene.g if scene.has('gravity') else 0.0)}    g         - gravity (along MoorDyn's -z = our +e3)",
        f"{density}    WtrDnsty  - {fluid_note}",
        f"{f(MOORDYN_DEPTH)}    WtrDpth   - no seabed contact",
        "0.0    TmaxIC    - no initial-condition solve (the state is overwritten)",
        "--------------------------- OUTPUTS -----------------------------------------------",
        "------------------------- need this line --------------------------------------",
        "",
    ])


@contextlib.contextmanager
def _quiet_c_output(log_path: Path):
    """Send the C/C++ stdout and stderr of the block to a file (MoorDyn prints a banner)."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(log_path, "ab") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _read_state(path: Path):
    """MoorDyn state file: header b'MoorDyn' + 2 version bytes, uint64 size, uint64 count, then
    per instance uint64 rows, uint64 cols and rows × cols doubles (position, velocity rows)."""
    raw = path.read_bytes()
    if raw[:7] != b"MoorDyn":
        raise RuntimeError(f"{path}: not a MoorDyn state file")
    head, off = raw[:25], 25
    count = struct.unpack("<Q", raw[17:25])[0]
    blocks = []
    for _ in range(count):
        n, m = struct.unpack("<QQ", raw[off:off + 16])
        off += 16
        blocks.append(np.frombuffer(raw, "<f8", n * m, off).reshape(n, m).copy())
        off += 8 * n * m
    if off != len(raw):
        raise RuntimeError(f"{path}: {len(raw) - off} unexpected trailing bytes")
    return head, blocks


def _write_state(path: Path, head: bytes, blocks) -> None:
    body = b"".join(struct.pack("<QQ", *b.shape) + b.astype("<f8").tobytes() for b in blocks)
    path.write_bytes(head + body)


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
        and first-call set-up), else the whole run's mean."""
        if "interval_s" in self.extra:
            return 1e6 * float(np.median(self.extra["interval_s"])) / self.extra["steps_per_interval"]
        return 1e6 * self.wall_s / self.steps if self.steps else float("nan")


def run_moordyn(scene: Scene, times, dt: float | None = None, workdir: Path | None = None) -> CodeRun:
    """Tip positions of MoorDyn at ``times`` (times[0] = 0, evenly spaced, multiples of dt)."""
    import moordyn

    dt = time_step(scene) if dt is None else dt
    times = np.asarray(times, float)
    steps_per_out = _steps_per_interval(times, dt)
    start = _initial_nodes(scene)
    q, v = start.q, start.v
    N = scene.string.elements
    shift = _md_offset(scene)
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        tmp = Path(tmp)
        inp = tmp / "line.txt"
        inp.write_text(moordyn_input(scene, dt))
        log = tmp / "moordyn.log"
        with _quiet_c_output(log):
            sys_ = moordyn.Create(str(inp))
            moordyn.SetVerbosity(sys_, moordyn.LEVEL_ERR)
            if moordyn.Init_NoIC(sys_, [], []) != 0:
                raise RuntimeError(f"MoorDyn init failed; log: {log.read_text()[-2000:]}")
            point = moordyn.GetPoint(sys_, 2)
            p0 = np.array(moordyn.GetPointPos(point))
            # replace MoorDyn's initial line shape by ours (see the module docstring)
            state = tmp / "state.bin"
            moordyn.SaveState(sys_, str(state))
            head, blocks = _read_state(state)
            line_block = blocks[-1]  # lines come last in MoorDyn's state
            if line_block.shape != (N - 1, 6):
                raise RuntimeError(f"MoorDyn state: line block {line_block.shape}, expected {(N - 1, 6)}")
            line_block[:, :3] = q[1:-1] @ TO_MOORDYN.T + shift
            line_block[:, 3:] = v[1:-1] @ TO_MOORDYN.T
            tips = [i for i, b in enumerate(blocks[:-1]) if b.shape == (1, 6) and np.allclose(b[0, :3], p0, atol=1e-12)]
            if len(tips) != 1:
                raise RuntimeError("MoorDyn state: cannot identify the free point's block")
            blocks[tips[0]][0, :3] = TO_MOORDYN @ q[-1] + shift
            blocks[tips[0]][0, 3:] = TO_MOORDYN @ v[-1]
            _write_state(state, head, blocks)
            moordyn.LoadState(sys_, str(state))
            out, intervals = [q[-1]], []
            for k in range(1, len(times)):
                t0 = time.perf_counter()
                moordyn.Step(sys_, [], [], float(times[k - 1]), float(times[k] - times[k - 1]))
                intervals.append(time.perf_counter() - t0)
                out.append(TO_MOORDYN @ (np.array(moordyn.GetPointPos(point)) - shift))
            moordyn.Close(sys_)
    return CodeRun("moordyn", N, dt, np.array(out), int(steps_per_out * (len(times) - 1)), float(sum(intervals)),
                   {"version": moordyn_version(), "interval_s": intervals, "steps_per_interval": steps_per_out})


def moordyn_version() -> str:
    from importlib.metadata import version

    return version("moordyn")


def _steps_per_interval(times, dt) -> int:
    dt_out = times[1] - times[0]
    n = round(dt_out / dt)
    if n < 1 or abs(n * dt - dt_out) > 1e-9 * dt_out or not np.allclose(np.diff(times), dt_out, rtol=1e-12, atol=1e-12):
        raise ValueError(f"output times must be evenly spaced multiples of dt = {dt:g} s (got spacing {dt_out:g} s)")
    return n


# ------------------------------------------------------------------------------------------
# MuJoCo
# ------------------------------------------------------------------------------------------
def _combined_inertia(m_b, J_c, rho, m_n):
    """Mass, CoM and inertia about the CoM of the body (m_b, J_c at ρ_c) plus a point mass m_n at
    the body-frame origin (the last string node's lumped mass)."""
    M = m_b + m_n
    com = m_b * rho / M
    def shift(m, r):
        return m * (r @ r * np.eye(3) - np.outer(r, r))
    J = J_c + shift(m_b, rho - com) + shift(m_n, -com)
    return M, com, J


def mujoco_xml(scene: Scene, dt: float) -> str:
    """MuJoCo MJCF of the scene's lumped chain (and free rigid body, if any)."""
    check_translatable(scene, "mujoco")
    st = scene.string
    N = st.elements
    l = scene.initial.deployed_length / N
    mu_l = st.mass_per_length * l
    start = _initial_nodes(scene)
    q, R0 = start.q, start.R
    f = "{:.17g}".format
    vec = lambda a: " ".join(f(x) for x in a)  # noqa: E731
    g = scene.g if scene.has("gravity") else 0.0
    lines = [
        '<mujoco model="reelbench_xval">',
        f'  <!-- scene {scene.name}, N = {N}: generated by benchmark/studies/xval.py; frame = ours (e3 down) -->',
        f'  <option timestep="{f(dt)}" integrator="RK4" gravity="0 0 {f(g)}" density="0" viscosity="0">',
        '    <flag contact="disable"/>',
        '  </option>',
        '  <worldbody>',
        f'    <site name="s1" pos="{vec(q[0])}"/>',
    ]
    for a in range(2, N + 2):
        last = a == N + 1
        if last and scene.has("rigid_body"):
            from reelbench.models.model import rot_to_quat

            M, com, J = _combined_inertia(scene.body.mass, scene.inertia, np.array(scene.body.attachment_to_com), mu_l / 2)
            full = [J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2]]
            lines += [
                f'    <body name="body" pos="{vec(q[-1])}" quat="{vec(rot_to_quat(R0))}">',
                '      <freejoint name="body"/>',
                f'      <inertial pos="{vec(com)}" mass="{f(M)}" fullinertia="{vec(full)}"/>',
                f'      <site name="s{a}" pos="0 0 0"/>',
                '    </body>',
            ]
            continue
        mass = mu_l / 2 + scene.body.mass if last else mu_l
        lines += [
            f'    <body name="n{a}" pos="{vec(q[a - 1])}">',
            *(f'      <joint name="n{a}{c}" type="slide" axis="{ax}"/>' for c, ax in (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1"))),
            # a point body on slide joints: its rotational inertia never enters (any positive value)
            f'      <inertial pos="0 0 0" mass="{f(mass)}" diaginertia="1 1 1"/>',
            f'      <site name="s{a}" pos="0 0 0"/>',
            '    </body>',
        ]
    lines += ['  </worldbody>', '  <tendon>']
    for a in range(1, N + 1):
        lines.append(f'    <spatial name="e{a}" stiffness="{f(st.axial_stiffness / l)}" springlength="{f(l)}" damping="0">'
                     f'<site site="s{a}"/><site site="s{a + 1}"/></spatial>')
    lines += ['  </tendon>', '</mujoco>', '']
    return "\n".join(lines)


def run_mujoco(scene: Scene, times, dt: float | None = None) -> CodeRun:
    import mujoco

    dt = time_step(scene) if dt is None else dt
    times = np.asarray(times, float)
    n_sub = _steps_per_interval(times, dt)
    model = mujoco.MjModel.from_xml_string(mujoco_xml(scene, dt))
    data = mujoco.MjData(model)
    start = _initial_nodes(scene)
    v, om = start.v, start.omega
    N = scene.string.elements
    n_slide = N - 1 if scene.has("rigid_body") else N
    data.qvel[: 3 * n_slide] = v[1:n_slide + 1].ravel()
    if scene.has("rigid_body"):
        # free joint: linear velocity of the frame origin (world), angular velocity (body frame)
        data.qvel[3 * n_slide:3 * n_slide + 3] = v[-1]
        data.qvel[3 * n_slide + 3:3 * n_slide + 6] = om
    site = model.site(f"s{N + 1}").id

    def tip():
        mujoco.mj_kinematics(model, data)
        return data.site_xpos[site].copy()

    out, intervals = [tip()], []
    for _ in range(1, len(times)):
        t0 = time.perf_counter()
        mujoco.mj_step(model, data, nstep=n_sub)
        intervals.append(time.perf_counter() - t0)
        out.append(tip())
    return CodeRun("mujoco", N, dt, np.array(out), n_sub * (len(times) - 1), float(sum(intervals)),
                   {"version": mujoco.__version__, "interval_s": intervals, "steps_per_interval": n_sub})


# ------------------------------------------------------------------------------------------
# Ours
# ------------------------------------------------------------------------------------------
def _min_strain(model, xs) -> float:
    """The smallest element strain over the saved states: MoorDyn's lines are tension-only, so
    it agrees with ours only while every element stays stretched."""
    return float((np.array([np.asarray(model.tensions(xi)).min() for xi in xs]) / model.EA).min())


def run_ours(scene: Scene, times, cache_dir: str | Path = CACHE_DIR) -> CodeRun:
    """Tip positions of our model (the scene's own mass model) at ``times`` (evenly spaced from
    0): the benchmark's reference solution (`benchmark.core.reference.get_reference`, cached in
    ``cache_dir``). Its cost is per right-hand side (DOP853 takes 12 per step)."""
    from reelbench.models import build_model

    times = np.asarray(times, float)
    ref = get_reference(scene, float(times[-1]), float(times[1] - times[0]), Path(cache_dir))
    if len(ref.t) != len(times) or not np.allclose(ref.t, times, atol=1e-9):
        raise RuntimeError(f"reference saved times {ref.t[:3]}… do not match the output times")
    model = build_model(scene)
    nfev = int(ref.stats["rhs_evals"])
    return CodeRun(f"ours_{scene.string.mass_model}", model.N, None, body_positions(model, ref), nfev,
                   float(ref.stats["wall_time"]), {"rhs_evals": nfev, "min_strain": _min_strain(model, ref.x)})


def run_ours_lgvi(scene: Scene, times, dt: float) -> CodeRun:
    """Tip positions of our model by our LGVI (fixed step ``dt``, compile time excluded).

    The study's own runs: second order, so at the outside codes' CFL-limited dt divided by
    `OURS_REFINE` its time error is far below the spatial differences (the lumped-vs-MoorDyn
    and lumped-vs-MuJoCo rows of the tables measure it: same discrete model)."""
    from reelbench.integrators.lgvi import LGVI
    from reelbench.models import build_model

    times = np.asarray(times, float)
    _steps_per_interval(times, dt)
    tr = LGVI().solve(scene, t_end=float(times[-1]), dt=dt, save_every=float(times[1] - times[0]))
    if not tr.ok:
        raise RuntimeError(f"lgvi failed on {scene.name} at dt = {dt:g}: {tr.reason}")
    if len(tr.t) != len(times) or not np.allclose(tr.t, times, atol=1e-9):
        raise RuntimeError(f"lgvi saved times {tr.t[:3]}… do not match the output times")
    model = build_model(scene)
    return CodeRun(f"ours_{scene.string.mass_model}", model.N, dt, body_positions(model, tr), int(tr.stats["steps"]),
                   float(tr.stats["wall_time"]), {"min_strain": _min_strain(model, tr.x), "method": "lgvi"})


#: our LGVI runs at the outside codes' dt / OURS_REFINE (within 1 % of its step before `CFL` was
#: halved, dt/4 at 0.05: its rows of the cost table and the convergence study barely change)
OURS_REFINE = 2
#: the code name of an outside code's rerun at dt/2 (its time-error check)
HALF_DT = "_half_dt"
#: the code name of our lumped model's reference (DOP853) solution: the equal-N comparison's
REFERENCE_CODE = "ours_lumped_dop853"


# ------------------------------------------------------------------------------------------
# The study: N sequence, tables, plots, README
# ------------------------------------------------------------------------------------------
#: Cases and the outside codes that get them: the scene without its rigid body (point mass
#: m_b at the tip), when the scene has one the scene itself, and the point mass in water
#: (buoyancy and Morison drag, `WATER`; MoorDyn only).
CASES = {"point_mass": ("moordyn", "mujoco"), "rigid_body": ("mujoco",), "in_water": ("moordyn",)}


def case_scene(scene: Scene, case: str) -> Scene:
    """The scene of one case: ``point_mass`` drops `rigid_body` and Ω0, ``rigid_body`` keeps it (both in
    vacuum: without the fluid effects), ``in_water`` is ``point_mass`` with buoyancy and drag (`WATER`
    unless the scene has its own)."""
    if case == "point_mass":
        return scene.with_(effects=[e for e in scene.effects if e not in ("rigid_body",) + FLUID_EFFECTS],
                           angular_velocity=[0.0, 0.0, 0.0])
    if case == "in_water":
        dry = [e for e in scene.effects if e != "rigid_body"]
        if all(scene.has(e) for e in FLUID_EFFECTS):
            return scene.with_(effects=dry, angular_velocity=[0.0, 0.0, 0.0])
        return scene.with_(effects=[e for e in dry if e not in FLUID_EFFECTS] + list(FLUID_EFFECTS),
                           angular_velocity=[0.0, 0.0, 0.0], **WATER)
    if case == "rigid_body":
        if not scene.has("rigid_body"):
            raise ValueError(f"case 'rigid_body' needs effect 'rigid_body' in scene {scene.name!r}")
        return scene.with_(effects=[e for e in scene.effects if e not in FLUID_EFFECTS])
    raise ValueError(f"unknown case {case!r}: allowed {', '.join(CASES)}")


def cases_of(scene: Scene) -> tuple[str, ...]:
    return ("point_mass", "rigid_body", "in_water") if scene.has("rigid_body") else ("point_mass", "in_water")


def check_scene(scene: Scene) -> None:
    """Refuse (`Untranslatable`) a scene that some code of some case cannot represent."""
    check_translatable(scene, "mujoco")
    for case in cases_of(scene):
        for code in CASES[case]:
            check_translatable(case_scene(scene, case), code)


OUTPUT_INTERVAL = 0.05  # s between compared samples


def _dt_for(scene: Scene, interval: float) -> float:
    """`time_step` rounded down so that it divides the output interval."""
    return interval / math.ceil(interval / time_step(scene) - 1e-9)


@dataclass
class Study:
    """The raw runs of the study: the compared times, and {(case, N): {code: CodeRun}}."""

    times: np.ndarray
    runs: dict

    def cases(self) -> list[str]:
        return sorted({c for c, _ in self.runs}, key=list(CASES).index)

    def elements(self, case: str) -> list[int]:
        return sorted(N for c, N in self.runs if c == case)


class Job(NamedTuple):
    """One (case, N) of the study: every code of the case on the scene at N elements."""

    scene: Scene  # the case's scene at the study's horizon
    case: str
    N: int
    times: np.ndarray


def run_job(job: Job) -> dict:
    """The row of one (case, N): the LGVI runs of our two mass models, our lumped model's reference
    (DOP853) solution (`REFERENCE_CODE`, computed in a temporary cache: never the shared one), and
    each of the case's outside codes at dt and at dt/2 (``<code>_half_dt``)."""
    sc = job.scene.with_(elements=job.N, mass_model="lumped")
    dt = _dt_for(sc, OUTPUT_INTERVAL)
    runs = {"ours_consistent": run_ours_lgvi(job.scene.with_(elements=job.N, mass_model="consistent"), job.times,
                                             dt / OURS_REFINE),
            "ours_lumped": run_ours_lgvi(sc, job.times, dt / OURS_REFINE)}
    with tempfile.TemporaryDirectory(prefix="xval-reference-") as tmp:
        ref = run_ours(sc, job.times, tmp)
    runs[REFERENCE_CODE] = CodeRun(REFERENCE_CODE, ref.N, None, ref.tip, ref.steps, ref.wall_s, ref.extra)
    for code in CASES[job.case]:
        run = run_moordyn if code == "moordyn" else run_mujoco
        runs[code] = run(sc, job.times, dt)
        runs[code + HALF_DT] = run(sc, job.times, dt / 2)
        runs[code + HALF_DT].code = code + HALF_DT
    return {"case": job.case, "N": job.N, "dt": dt, "runs": runs}


def _describe(row: dict) -> str:
    return (f"xval {row['case']} N={row['N']}: dt={row['dt']:.3g} s; "
            + ", ".join(f"{k} {r.wall_s:.2f} s" for k, r in row["runs"].items()))


def study(scene: Scene, elements=DEFAULT_ELEMENTS, t_end: float = DEFAULT_T_END, cases=None,
          log=engine.log_stderr) -> Study:
    """Run every code of every case at every N, one engine job per (case, N) in this process
    (their per-step costs are compared, so they never share the cores)."""
    check_scene(scene)  # refuse before any work
    times = np.linspace(0.0, t_end, round(t_end / OUTPUT_INTERVAL) + 1)
    jobs = [Job(case_scene(scene, case).with_(t_end=t_end), case, N, times)
            for case in cases or cases_of(scene) for N in elements]
    rows = engine.run_jobs(run_job, jobs, workers=0, describe=_describe, log=log)
    return Study(times, {(r["case"], r["N"]): r["runs"] for r in rows})


# ------------------------------------------------------------------------------------------
# An earlier study in the output directory, rebuilt from the raw tips and the cost table it wrote
# ------------------------------------------------------------------------------------------
def earlier_xval(out: Path, scene, t_end: float, this_run: set) -> tuple[dict, dict]:
    """The (case, N) runs of the cross-validation already in ``out`` that this run (``this_run``:
    its (case, N)) does not recompute, rebuilt from ``tips.npz`` (the tips), ``cost.csv`` (steps,
    time, strain) and ``settings.json`` (scene, horizon, each run's physics hash): ({(case, N):
    {code: CodeRun}}, {(case, N): its settings entry}). ValueError before any work when ``out``
    holds such runs that cannot join this run's (another scene, horizon or scene values, or files
    missing): writing the study would drop them."""
    import json

    import numpy as np
    import pandas as pd

    from reelbench.benchmark.core.store import UnreadableFile, read_npz

    out = Path(out)
    files = [out / n for n in ("settings.json", "cost.csv", "tips.npz")]
    if not any(f.exists() for f in files):
        return {}, {}
    refuse = (f"{out} holds an earlier cross-validation that this run cannot merge with and would overwrite ({{}}): "
              "give --elements (and --scenes, --t-end) covering it, another --out, or move it away")
    try:
        settings = json.loads(files[0].read_text(encoding="utf-8"))
        cost = pd.read_csv(files[1])
        tips = read_npz(files[2])
        earlier = {(str(r["case"]), int(r["N"])): r for r in settings["runs"]}
    except (OSError, ValueError, KeyError, TypeError, UnreadableFile, pd.errors.ParserError) as exc:
        raise ValueError(refuse.format(f"its files cannot be read: {type(exc).__name__}")) from None
    outside = sorted(k for k in earlier if k not in this_run)
    if not outside:
        return {}, {}
    times = np.linspace(0.0, t_end, round(t_end / OUTPUT_INTERVAL) + 1)
    if settings.get("scene") != scene.name or not np.isclose(float(settings.get("t_end", -1)), t_end):
        raise ValueError(refuse.format(f"scene {settings.get('scene')!r} to t = {settings.get('t_end')} s, this run's "
                                       f"{scene.name!r} to {t_end:g} s"))
    if tips.get("times") is None or np.shape(tips["times"]) != times.shape or not np.allclose(tips["times"], times):
        raise ValueError(refuse.format("its tips are at other times"))
    stale = [f"{c} N={n}" for c, n in outside
             if case_scene(scene, c).with_(elements=n, mass_model="lumped", t_end=t_end).key()
             != earlier[(c, n)].get("scene_key_lumped")]
    if stale:
        raise ValueError(refuse.format(f"{', '.join(stale)} computed with other scene values or an older model"))
    runs = {}
    for case, n in outside:
        rows = cost[(cost["case"] == case) & (cost["N"] == n)]
        runs[(case, n)] = {}
        for r in rows.to_dict("records"):
            tip = tips.get(f"{case}_N{n}_{r['code']}")
            if tip is None:
                raise ValueError(refuse.format(f"no tips of {r['code']} for {case} N={n} in tips.npz"))
            extra = {"min_strain": r["min_strain"]}
            if np.isfinite(r["us_per_step"]):  # the time per step it measured: one interval of that time
                extra.update(interval_s=[r["us_per_step"] * 1e-6], steps_per_interval=1)
            if np.isfinite(r["us_per_rhs"]) and r["us_per_rhs"] > 0:
                extra["rhs_evals"] = 1e6 * r["wall_s"] / r["us_per_rhs"]
            dt = r["dt_s"] if np.isfinite(r["dt_s"]) else None
            runs[(case, n)][str(r["code"])] = CodeRun(str(r["code"]), n, dt, np.asarray(tip), int(r["steps"]),
                                                       float(r["wall_s"]), extra)
    return runs, {k: earlier[k] for k in outside}


def run_xval(scene_name: str, elements, t_end: float, out: Path, *, command: str = "python -m benchmark xval",
             log: Callable[[str], None] = log_stderr, cases=None) -> int:
    """The cross-validation against MoorDyn and MuJoCo into ``out``; returns the exit status. The runs
    of an earlier study in ``out`` that this one does not recompute (other N) are kept and every
    file is written from the merged study (`earlier_xval`, which refuses,
    before any work, earlier runs that cannot be kept). The study writes when it ends: a stopped
    one leaves ``out`` as it was."""
    from reelbench.benchmark.studies import xval_report
    from reelbench.benchmark.core.report import earlier_runs
    from reelbench.models import load_scene

    out = Path(out)
    provenance = Provenance(command)
    scene = load_scene(scene_name)
    check_scene(scene)  # refuses an untranslatable scene before any work
    this_run = {(c, int(n)) for c in (cases or cases_of(scene)) for n in elements}
    kept, kept_settings = earlier_xval(out, scene, t_end, this_run)
    try:
        result = study(scene, elements, t_end, cases=cases, log=log)
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, f"{out}/ is as it was (the study writes its files when it ends)", log)
    if kept:
        log(f"xval: kept {len(kept)} earlier (case, N) run(s) of {out}/ as they were: "
            + ", ".join(f"{c} N={n}" for c, n in sorted(kept)))
        result = Study(result.times, {**kept, **result.runs})
        provenance = provenance.merged_into(earlier_runs(out / "README.md"))
    log(f"wrote {xval_report.write_outputs(result, scene, out, provenance, kept=kept_settings)}")
    return 0
