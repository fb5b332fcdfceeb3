"""The one small interface every integrator implements, and what it returns.

An integrator is a class with a ``name``, declared ``capabilities`` and a ``solve`` method::

    traj = integrator.solve(scene, t_end, dt=..., rtol=..., atol=..., save_every=...,
                            max_steps=..., time_limit=...)

``solve`` never raises for a run that fails numerically (Newton failure, divergence, step
size collapse, the deployed length leaving its range) or runs out of its budget (``max_steps``,
``time_limit``): it returns the trajectory up to the last good step with ``status`` naming what
happened and ``reason`` saying it in words. Bad *arguments* (a negative dt, a missing
tolerance, a tolerance given to a fixed-step method) raise ``ValueError`` before any work.

Nothing here imports JAX: the registry's names and each class's declarations are available
without it (the command line refuses bad input in a fraction of a second).
"""

from __future__ import annotations

import abc
import enum
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np


class Capability(str, enum.Enum):
    """What a method is, declared by each integrator (never guessed by the runner)."""

    FIXED_STEP = "fixed_step"  # takes dt
    ADAPTIVE = "adaptive"  # takes rtol/atol
    IMPLICIT = "implicit"  # solves a nonlinear system per step
    VARIATIONAL = "variational"  # discrete Euler–Lagrange equations (symplectic, momentum-preserving)
    GROUP_PRESERVING = "group_preserving"  # attitude stays on SO(3) to round-off


class Status(str, enum.Enum):
    OK = "ok"
    NEWTON_FAILED = "newton_failed"
    DIVERGED = "diverged"  # non-finite state, energy beyond `energy_bound`, or (LGVI) Cayley blow-up
    LENGTH_LIMIT = "length_limit"  # deployed length reached an end of (min_deployed_length, L - b)
    MAX_STEPS = "max_steps"
    TIME_LIMIT = "time_limit"  # the run's wall-clock budget (``time_limit``) ran out
    STEP_SIZE_COLLAPSE = "step_size_collapse"
    FAILED = "failed"  # any other solver failure, with the solver's message as reason


# The sets of statuses every reader asks, named here beside `Status` so that none re-lists them.
#: A finished run: the only status whose errors, costs and curve points count (`Trajectory.ok`).
FINISHED_STATUSES = (Status.OK.value,)
#: A run stopped by its own budget (steps, seconds): a finer setting costs more, so a search goes
#: no finer after one, and a ranking names the budget as the cause.
BUDGET_STATUSES = (Status.MAX_STEPS.value, Status.TIME_LIMIT.value)
#: Statuses a benchmark table has besides the integrators' own: the task raised (a bug), its
#: worker died, or it finished beyond a sanity bound (no solution: `benchmark.runs.metrics.INACCURATE`).
ERROR, CRASHED, INACCURATE = "error", "crashed", "inaccurate"
TABLE_ONLY_STATUSES = (ERROR, CRASHED, INACCURATE)
#: Rows with these statuses are recomputed on resume (the cause may have been transient: a
#: wall-clock budget runs out sooner on a loaded machine).
RETRY_STATUSES = (CRASHED, ERROR, Status.TIME_LIMIT.value)


def is_finished(status) -> bool:
    """Whether ``status`` is a finished run's (`FINISHED_STATUSES`)."""
    return status in FINISHED_STATUSES


@dataclass
class Trajectory:
    """Saved states of one run, in the integrator's own state, plus stats and status.

    Attributes:
        t: saved times, shape (n,).
        x: generalized coordinates (s_p if reel, q_2..q_{N+1}), shape (n, nx); see
            `models.layout`.
        attitude: rotation matrices (n, 3, 3) or quaternions (n, 4) (w, x, y, z), or None
            without a rigid body; ``attitude_kind`` says which.
        velocity: generalized velocities (ṡ_p, q̇, Ω), shape (n, nw), or None if the
            integrator carries momenta (then ``momentum`` is set; diagnostics invert the
            Legendre transform).
        momentum: generalized momenta, shape (n, nw), or None.
        work: accumulated work of the non-conservative forces, shape (n,).
        status / reason: ``"ok"`` or a `Status` value naming why the run stopped early.
        stats: per-run counters: ``steps``, ``rhs_evals``, ``jac_evals``, ``lu_decompositions``,
            ``newton_iterations``, ``rejected_steps``, ``wall_time`` (s, after compilation),
            ``compile_time`` (s) — those that apply.
        integrator / settings / scene_name: provenance.
        scene: the scene it was computed with (TOML-shaped, `models.Scene.to_dict`; set by
            ``simulate``, so that ``figures`` needs no scene file), or {} when not recorded.
    """

    t: np.ndarray
    x: np.ndarray
    attitude: np.ndarray | None
    velocity: np.ndarray | None
    work: np.ndarray
    momentum: np.ndarray | None = None
    attitude_kind: str = "matrix"  # "matrix" or "quaternion"
    status: str = Status.OK.value
    reason: str = ""
    stats: dict[str, Any] = field(default_factory=dict)
    integrator: str = ""
    settings: dict[str, Any] = field(default_factory=dict)
    scene_name: str = ""
    scene: dict[str, Any] = field(default_factory=dict)
    #: the solution between saved points, where a method records it on request (scipy's
    #: adapters with ``dense_output=True``: the reference's, `benchmark.core.reference.DenseSolution`);
    #: not a field: never saved with the trajectory
    dense: ClassVar[Any] = None

    @property
    def ok(self) -> bool:
        return is_finished(self.status)

    def __len__(self) -> int:
        return len(self.t)

    def save(self, path) -> None:
        """Write to .npz atomically (temporary file, then rename)."""
        import json

        from reelbench.models.io import atomic_path

        arrays = {k: v for k, v in (("t", self.t), ("x", self.x), ("attitude", self.attitude),
                                     ("velocity", self.velocity), ("momentum", self.momentum),
                                     ("work", self.work)) if v is not None}
        meta = {k: getattr(self, k) for k in ("attitude_kind", "status", "reason", "stats", "integrator",
                                              "settings", "scene_name", "scene")}
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(meta, default=str)), **arrays)

    @classmethod
    def load(cls, path) -> "Trajectory":
        import json

        with np.load(path) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {k: data[k] if k in data else None for k in ("t", "x", "attitude", "velocity", "momentum", "work")}
        return cls(**arrays, **meta)


def stamp_wall_time(traj: Trajectory, started: float) -> Trajectory:
    """Set ``traj.stats["wall_time"]``: one definition of run time for every integrator — the
    whole ``solve()`` call, from ``started`` (`time.perf_counter()` at its entry) to the finished
    `Trajectory` (output conversion included), minus ``stats["compile_time"]`` and minus
    ``stats["count_time"]`` (a counting replay after the run, Kvaerno5's). Call it last, on the
    trajectory about to be returned."""
    booked_apart = float(traj.stats.get("compile_time", 0.0)) + float(traj.stats.get("count_time", 0.0))
    traj.stats["wall_time"] = time.perf_counter() - started - booked_apart
    return traj


def build_model_timed(scene):
    """(model of ``scene``, seconds spent building it): 0.0 when `models.build_model` had it
    cached. A first build (which also starts JAX's backend) is one-time setup: the adapters book
    it with ``compile_time``, not with the run time of `stamp_wall_time`."""
    from reelbench.models import build_model

    misses = build_model.cache_info().misses
    t0 = time.perf_counter()
    model = build_model(scene)
    return model, (time.perf_counter() - t0 if build_model.cache_info().misses > misses else 0.0)


#: Without a save interval a run saves this many intervals of its horizon.
DEFAULT_SAVED_INTERVALS = 200


def save_interval(t_end: float, save_every: float | None) -> float:
    """``save_every``, or t_end / `DEFAULT_SAVED_INTERVALS` without one."""
    return t_end / DEFAULT_SAVED_INTERVALS if save_every is None else save_every


def save_times(t_end: float, save_every: float | None, dt: float | None = None) -> np.ndarray:
    """Saved times 0, Δ, 2Δ, ..., t_end. For a fixed step ``dt``: the step points nearest those
    times (`fixed_step_grid`), t_end last (the last step is shortened to land on it)."""
    if dt is not None:
        _, idx = fixed_step_grid(t_end, dt, save_every)
        return step_times(idx, dt, t_end)
    save_every = save_interval(t_end, save_every)
    n = int(math.floor(t_end / save_every + 1e-9))
    t = np.minimum(np.arange(n + 1) * save_every, t_end)  # no rounding overshoot past t_end
    return t if abs(t[-1] - t_end) < 1e-12 * max(1.0, t_end) else np.append(t, t_end)


#: A step count within this relative distance of t_end / dt is whole: dt divides t_end.
WHOLE_STEPS_TOL = 1e-9


def fixed_step_count(t_end: float, dt: float) -> int:
    """The number of steps a fixed-step run of ``dt`` takes to t_end: n - 1 of size dt and a last
    one that lands on t_end (dt itself when dt divides t_end, to `WHOLE_STEPS_TOL`). The one count
    of the loop, of its planned-step limit and of the command line's estimate."""
    return max(1, int(math.ceil(t_end / dt - WHOLE_STEPS_TOL)))


def fixed_step_grid(t_end: float, dt: float, save_every: float | None = None) -> tuple[int, np.ndarray]:
    """(n, idx): ``n`` steps reach t_end, n - 1 of size dt and the last one t_end - (n - 1) dt
    (dt itself when dt divides t_end), so that any step size ends at t_end; ``idx``: the step
    indices saved, 0, the step point nearest each saved time of `save_times` (any dt: nothing
    needs to divide the save interval), n last, in order and without repeats."""
    n = fixed_step_count(t_end, dt)
    grid = save_times(t_end, save_every)[:-1]  # its last time is t_end: step n
    idx = np.unique(np.minimum(np.rint(grid / dt), n).astype(np.int64))
    return n, (idx if idx[-1] == n else np.append(idx, n))


def last_step(t_end: float, dt: float, n: int) -> float:
    """The size of step n of `fixed_step_grid`: dt, or the shorter step that lands on t_end."""
    h = t_end - (n - 1) * dt
    return float(dt) if abs(h - dt) <= WHOLE_STEPS_TOL * dt else float(h)


def step_times(idx, dt: float, t_end: float) -> np.ndarray:
    """Times of fixed-step points ``idx`` (k dt; the last step point is t_end)."""
    return np.minimum(np.asarray(idx, dtype=float) * dt, t_end)


# --------------------------------------------------------------------------------------------
# Divergence guard on the energy balance, shared by every integrator
# --------------------------------------------------------------------------------------------
#: A run has *diverged* when its energy balance error |E − W − E0| exceeds this factor times
#: the scene's energy scale (`energy_scale`). The scale bounds every energy the motion can
#: legitimately exchange, so an error beyond it means the numbers are no longer a solution of
#: the scene (a blow-up grows exponentially, so the exact factor only shifts the stop by a few
#: steps). Every method checks it at its saved points only (integrators/README.md, "One guard
#: policy"), so that every method is timed over the same work.
ENERGY_GROWTH_FACTOR = 1.0


def energy_scale(model) -> float:
    """The scene's energy scale in J: the model's own (`models.StringPendulum.energy_scale`,
    which says what it covers)."""
    return model.energy_scale()


def energy_bound(model) -> float:
    """The largest energy balance error |E − W − E0| (J) a run may show before it is `diverged`."""
    return ENERGY_GROWTH_FACTOR * energy_scale(model)


def initial_energy(model) -> float:
    """E0: the energy of the scene's initial state (the reference of every energy guard)."""
    x0, R0, w0 = model.initial_state()
    return float(model.energy(x0, R0, w0))


def energy_error(model, x, R, w, W, E0):
    """|E(x, R, w) − W − E0| (traceable by JAX; w are velocities)."""
    from reelbench.models._jax import jnp

    return jnp.abs(model.energy(x, R, w) - W - E0)


def energy_error_ode(model, y, E0):
    """`energy_error` of a quaternion ODE state y = (x, quat, w, W) (`models.layout`)."""
    x, R, w, W = model.split_state(y)
    return energy_error(model, x, R, w, W, E0)


def energy_reason(err: float, bound: float, t: float, kept: str = "") -> str:
    """The `reason` of a run stopped by the energy guard."""
    return (f"energy balance error |E - W - E0| = {err:.4g} J at t = {t:.6g} s exceeds the bound "
            f"{bound:.4g} J (ENERGY_GROWTH_FACTOR x the scene's energy scale){kept}")


def check_positive(name: str, value, *, allow_none: bool = False) -> None:
    """Refuse a non-positive or non-finite argument before any work is done."""
    if value is None:
        if allow_none:
            return
        raise ValueError(f"{name} is required (allowed: a finite number > 0)")
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) or not (
        math.isfinite(value) and value > 0
    ):
        raise ValueError(f"{name} = {value!r} is invalid (allowed: a finite number > 0)")


#: The situations an integrator may declare its own order for (`Integrator.orders`).
SITUATIONS = ("fixed_length", "reel")


def situation(scene) -> str:
    """"reel" when the scene's deployed length is a degree of freedom, else "fixed_length".

    Read from the state layout (the effects that add s_p, `models.effects.Effect.state`), not
    from an effect's name."""
    from reelbench.models.layout import StateLayout

    return "reel" if StateLayout.from_scene(scene).has_reel else "fixed_length"


#: The values of `Integrator.implementation` the shipped methods declare: compiled by JAX/XLA
#: (the LGVI family, every `FixedStepMethod`, the diffrax adapters) or stepped in Python by scipy.
IMPLEMENTATIONS = ("jax-compiled", "scipy-python")


class Integrator(abc.ABC):
    """Base class of every integrator. Subclasses set the class attributes and `solve`.

    Class attributes:
        name: registry name (lower case).
        capabilities: frozenset of `Capability`, declared.
        implementation: how the method's steps run, copied into the results: one of
            `IMPLEMENTATIONS` for the shipped methods ("jax-compiled", "scipy-python"); a plugin
            says what it is (e.g. "numba").
        order: the method's classical order of accuracy (for convergence tests), or None.
        orders: optional per-situation orders where they differ from ``order``, keyed by
            `SITUATIONS` (e.g. the paper's LGVI: {"fixed_length": 2, "reel": 1}); see `order_for`.
        description: one line for tables and ``python -m benchmark list``.
        cost_hint: the method's rough cost (compile seconds, cost per step), which every study's
            scheduling and ETA read.

    A class says what the method is, never which study runs it at which setting: each study keeps
    its own choices in one table keyed by method name (the default sweep's members and tolerances
    in `benchmark.runs.sweep`, the energy study's plan in `benchmark.studies.horizon`, the
    stability map's default run in `benchmark.studies.stability`); a method a study does not list
    gets that study's general rule (integrators/README.md, "The plugin contract").

    Nothing in a class definition may need JAX: the registry lists and describes methods
    without importing it (JAX is imported inside the functions that trace and compile).
    """

    name: ClassVar[str] = ""
    capabilities: ClassVar[frozenset[Capability]] = frozenset()
    implementation: ClassVar[str] = "unspecified"
    order: ClassVar[int | None] = None
    orders: ClassVar[dict[str, int] | None] = None
    description: ClassVar[str] = ""
    #: (compile seconds per scene, run cost per step relative to an explicit RK step): a rough
    #: hint of what the method costs, for every study's scheduling (longest jobs first) and
    #: ETA, never a result
    cost_hint: ClassVar[tuple[float, float]] = (30.0, 1.0)

    def has(self, capability: Capability) -> bool:
        return capability in self.capabilities

    def order_for(self, scene) -> int | None:
        """The order this method has on ``scene``'s situation (`situation`), else ``order``."""
        return (self.orders or {}).get(situation(scene), self.order)

    @abc.abstractmethod
    def solve(
        self,
        scene,
        t_end: float | None = None,
        *,
        dt: float | None = None,
        rtol: float | None = None,
        atol: float | None = None,
        save_every: float | None = None,
        max_steps: int | None = None,
        time_limit: float | None = None,
        **options,
    ) -> Trajectory:
        """Integrate ``scene`` from 0 to ``t_end`` (default ``scene.t_end``).

        Fixed-step methods need ``dt`` and refuse tolerances; adaptive methods need ``rtol``
        and ``atol`` (and take ``dt`` as the initial step); a method that is both takes ``dt``
        alone (constant step) or ``rtol`` and ``atol`` (adaptive), never both. ``save_every``
        is the interval between saved times in seconds (default t_end/200; a fixed step
        saves at the step points nearest those times, any dt allowed, and its last step is
        shortened to end at t_end). ``max_steps`` bounds the steps, ``time_limit`` the
        run's wall-clock seconds (after compilation); running out of either ends the run with
        status ``max_steps`` / ``time_limit``. Returns a `Trajectory`.
        """

    def __repr__(self) -> str:
        return f"<integrator {self.name!r}>"
