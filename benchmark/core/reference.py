"""Reference solutions of the runs table and the answer: DOP853 at rtol 1e-12 / atol 1e-14 on the
closed-form right-hand side (the scipy adapter's default; `benchmark.core.policy.REFERENCE_METHOD`, which
also says why the order ladders and `verify` use references of their own), computed once per
problem, cached, reused.

The cache key is a hash of the scene (its physics, not its name), the horizon, the save
interval and the reference method's settings, so a changed scene never reuses a stale file;
the file's identity also holds a hash of the model and integrator source, so a reference
computed by other code is recomputed too.

A cached file is trusted only after it proves what it is: it carries its identity (scene
hash, horizon, save interval, solver and tolerances, and the package versions that computed
it) and a SHA-256 checksum of its arrays and identity. A file that fails to load (truncated,
not an .npz, random bytes), belongs to another problem, or whose numbers no longer match
their checksum (edited, scaled) is reported by file name and recomputed, never used.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.policy import REFERENCE_METHOD  # noqa: F401 (its settings: the one rule)
from reelbench.benchmark.core.store import (PHYSICS_DIRS, UnreadableFile, read_npz, source_hash, trajectory_from, trajectory_parts,
                             write_npz)
from reelbench.integrators import get_integrator
from reelbench.models.io import inside, user_cache_dir

#: References are shared by every study and output directory: one file per scene, horizon, save
#: interval and physics code (`reference_path`).
CACHE_DIR = user_cache_dir() / "references"
#: Version of the file layout below; a file of another format is recomputed (3: with the dense
#: output of the compared components, `DenseSolution`).
FORMAT = 3
# The source a reference is computed by (DOP853 through the scipy adapter, on the closed-form
# right-hand side) is `benchmark.core.store.PHYSICS_DIRS`, the physics every row's code version covers.


def identity(scene, t_end: float, save_every: float) -> dict:
    """What a reference is: everything that determines its numbers, the code that computes it
    included (``physics``), so that a changed model is never compared with a stale reference."""
    return {"format": FORMAT, "scene": scene.key(), "t_end": float(t_end), "save_every": float(save_every),
            "physics": source_hash(PHYSICS_DIRS), **REFERENCE_METHOD}


def reference_path(scene, t_end: float, save_every: float, cache_dir: Path = CACHE_DIR) -> Path:
    """The file of a reference: one per problem and physics code (a file found there is still
    checked against its whole identity before it is used)."""
    key = json.dumps({"scene": scene.key(), "t_end": t_end, "save_every": save_every, **REFERENCE_METHOD,
                      "physics": source_hash(PHYSICS_DIRS)}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return inside(cache_dir, f"reference-{scene.name}-{digest}.npz")


def _versions() -> dict:
    out = {}
    for p in ("numpy", "scipy", "jax", "jaxlib"):
        try:
            out[p] = importlib.metadata.version(p)
        except importlib.metadata.PackageNotFoundError:
            pass
    return out


def checksum(arrays: dict, header: str) -> str:
    """SHA-256 over the header text and every array's name, dtype, shape and bytes."""
    h = hashlib.sha256(header.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class DenseSolution:
    """The reference between its saved points: DOP853's own interpolant of every step (order 7,
    `scipy.integrate`'s ``Dop853DenseOutput``), so that a run is compared with the reference at
    the times the run saved, whatever its step (a fixed step saves at its step points nearest
    the save times, `integrators.base.fixed_step_grid`). Only the components the reference
    metrics compare are kept (the body's coordinates, the last three of x, and the attitude
    quaternion: ``columns`` of the ODE state), which keeps the file small (the whole state of
    N = 40 over 10 s took 256 MB).

    ``t``: the step boundaries (n + 1,); ``y0``: the kept components at each step's start
    (n, k); ``F``: each step's interpolation coefficients of them (n, 7, k)."""

    ARRAYS = ("dense_t", "dense_y0", "dense_F", "dense_columns")

    def __init__(self, t, y0, F, columns):
        self.t, self.y0, self.F = (np.asarray(a, dtype=float) for a in (t, y0, F))
        self.columns = np.asarray(columns, dtype=np.int64)

    @staticmethod
    def compared_columns(layout) -> np.ndarray:
        """The ODE state's components the reference metrics compare (`benchmark.runs.metrics`)."""
        x = np.arange(layout.y_x.start, layout.y_x.stop)[-3:]
        quat = np.arange(layout.y_quat.start, layout.y_quat.stop) if layout.has_attitude else np.zeros(0, int)
        return np.concatenate([x, quat]).astype(np.int64)

    @classmethod
    def from_steps(cls, pieces, columns) -> "DenseSolution":
        """From the interpolants of every step in order (`Trajectory.dense` of a DOP853 solve
        with ``dense_output=True``), kept for ``columns`` of the state."""
        if not pieces or not all(hasattr(p, "F") for p in pieces):
            raise ValueError("the reference's dense output needs DOP853's interpolants (attribute F)")
        c = np.asarray(columns, dtype=np.int64)
        t = np.array([pieces[0].t_old] + [p.t for p in pieces])
        return cls(t, np.stack([p.y_old[c] for p in pieces]), np.stack([p.F[:, c] for p in pieces]), c)

    def arrays(self) -> dict:
        return dict(zip(self.ARRAYS, (self.t, self.y0, self.F, self.columns)))

    def __call__(self, times) -> np.ndarray:
        """The kept components at ``times`` (inside [t_0, t_n]), (len(times), len(columns))."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if times.size and (times.min() < self.t[0] - 1e-12 or times.max() > self.t[-1] * (1 + 1e-12) + 1e-12):
            raise ValueError(f"reference: times {times.min():g}..{times.max():g} s leave its range "
                             f"{self.t[0]:g}..{self.t[-1]:g} s (it is never extrapolated)")
        i = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self.F) - 1)
        x = ((times - self.t[i]) / (self.t[i + 1] - self.t[i]))[:, None]
        y = np.zeros((len(times), self.y0.shape[1]))
        for k, f in enumerate(self.F[i].transpose(1, 0, 2)[::-1]):  # scipy's Horner-like scheme
            y += f
            y *= x if k % 2 == 0 else 1 - x
        return y + self.y0[i]


def reference_at(scene, ref, times):
    """The reference trajectory at ``times`` (a run's saved times), from its dense output: the
    components it keeps (`DenseSolution`), every other one NaN (only the body's position and
    attitude are compared with it); the trajectory ``ref`` itself where it has none (then only
    the saved times both share compare)."""
    from reelbench.integrators.lifecycle import ode_trajectory
    from reelbench.models import build_model

    if ref.dense is None:
        return ref
    model = build_model(scene)
    times = np.asarray(times, dtype=float)
    y = np.full((len(times), model.layout.ny), np.nan)
    y[:, ref.dense.columns] = ref.dense(times)
    return ode_trajectory(model, scene, times, y, status=ref.status, reason="", stats={},
                          integrator=ref.integrator, settings=ref.settings)


def save_reference(traj, path: Path, ident: dict) -> None:
    """Write ``traj`` with its identity and checksum, atomically (its dense output too)."""
    arrays, meta = trajectory_parts(traj)
    if traj.dense is not None:
        arrays.update(traj.dense.arrays())
    header = json.dumps({"identity": ident, "versions": _versions(),
                         "meta": json.dumps(meta, default=str, sort_keys=True)}, sort_keys=True)
    write_npz(path, {"header": np.array(header), "checksum": np.array(checksum(arrays, header)), **arrays})


class ReferenceFailed(ValueError):
    """The reference solve of a scene did not finish (its step budget ran out, or it diverged):
    the scene is at fault more often than the solver, so the message names it and its fix."""


class CacheError(ValueError):
    """A cached reference that cannot be trusted (the message says why)."""


def load_reference(path: Path, ident: dict):
    """The trajectory in ``path`` if it loads, is the reference ``ident`` describes and matches
    its checksum; CacheError saying what is wrong otherwise."""
    try:
        data = read_npz(path)
    except UnreadableFile as exc:
        raise CacheError(f"cannot be read ({exc})") from None
    if "header" not in data or "checksum" not in data:
        raise CacheError("no identity or checksum (written by an older version or another program)")
    header, stored = str(data.pop("header")), str(data.pop("checksum"))
    try:
        head = json.loads(header)
        got = head["identity"]
        meta = json.loads(head["meta"])
    except (ValueError, KeyError, TypeError) as exc:
        raise CacheError(f"its header is not valid ({exc})") from None
    if got != ident:
        diff = sorted(k for k in set(got) | set(ident) if got.get(k) != ident.get(k))
        raise CacheError(f"it is a different reference (differs in {', '.join(diff)})")
    if checksum(data, header) != stored:
        raise CacheError("its numbers do not match their checksum (the file was changed after it was written)")
    if any(k not in data for k in DenseSolution.ARRAYS):
        raise CacheError("it has no dense output")
    traj = trajectory_from(data, meta)
    traj.dense = DenseSolution(*(data[k] for k in DenseSolution.ARRAYS))
    return traj


def get_reference(scene, t_end: float, save_every: float, cache_dir: Path = CACHE_DIR, log=log_stderr):
    """The cached reference for (scene, t_end, save_every), computing it on first use, or when
    the cached file cannot be trusted (reported through ``log`` by file name)."""
    from reelbench.models import build_model

    path = reference_path(scene, t_end, save_every, cache_dir)
    ident = identity(scene, t_end, save_every)
    if path.exists():
        try:
            return load_reference(path, ident)
        except CacheError as exc:
            if log:
                log(f"warning: cached reference {path} is not used: {exc}; recomputing it")
    if log:
        log(f"reference: computing {scene.name} to t = {t_end:g} s with {REFERENCE_METHOD} ...")
    integ = get_integrator(REFERENCE_METHOD["integrator"])
    traj = integ.solve(scene, t_end=t_end, rtol=REFERENCE_METHOD["rtol"], atol=REFERENCE_METHOD["atol"],
                       save_every=save_every, dense_output=True)
    if not traj.ok:
        raise ReferenceFailed(
            f"the reference solution of scene {scene.name!r} ({REFERENCE_METHOD['integrator']}, rtol "
            f"{REFERENCE_METHOD['rtol']:g}) did not reach t = {t_end:g} s: {traj.status}: {traj.reason}. Check the scene's "
            "values (lengths, stiffness, masses, speeds: a scene can validate and still be too stiff to integrate), "
            "or give a shorter --t-end")
    traj.dense = DenseSolution.from_steps(traj.dense, DenseSolution.compared_columns(build_model(scene).layout))
    try:
        save_reference(traj, path, ident)
    except OSError as exc:  # a full disk costs the cache, not the study
        if log:
            log(f"warning: {exc}; the reference of {scene.name} is used without being cached")
    return traj


class ReferenceProblem(NamedTuple):
    """A reference some jobs share, by what a task names: the scene (name or path, with its
    overrides), the horizon (None: the scene's t_end) and the save interval."""

    scene: str
    overrides: tuple
    t_end: float | None
    save_every: float


def prepare_reference(problem: ReferenceProblem, cache_dir: str | Path = CACHE_DIR) -> None:
    """Compute (or check) the cached reference of ``problem`` before the jobs read it, so that
    two workers never compute the same one."""
    from reelbench.models import load_scene

    scene = load_scene(problem.scene, **dict(problem.overrides))
    get_reference(scene, problem.t_end if problem.t_end is not None else scene.t_end, problem.save_every,
                  Path(cache_dir))
