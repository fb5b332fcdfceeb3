"""Reference solutions: computed once per scene at tight tolerance, cached, reused.

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

import functools
import hashlib
import importlib.metadata
import json
import sys
from pathlib import Path

import numpy as np

from integrators import Trajectory, get_integrator

REFERENCE_METHOD = {"integrator": "dop853", "rtol": 1e-12, "atol": 1e-14}
CACHE_DIR = Path("results") / "cache"
#: Version of the file layout below; a file of another format is recomputed.
FORMAT = 2
_ARRAYS = ("t", "x", "attitude", "velocity", "momentum", "work")


def _log_stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


#: The source a reference is computed by: the model and the integrators (DOP853 through the
#: scipy adapter, on the closed-form right-hand side).
PHYSICS_DIRS = ("models", "integrators")


@functools.lru_cache(maxsize=8)
def source_hash(dirs: tuple = (), files: tuple = ()) -> str:
    """A hash of the Python and TOML source under ``dirs`` and of ``files`` (paths relative to
    the repository root), names included: it changes when any of that code does. Read once per
    process (the code a process runs does not change under it)."""
    root = Path(__file__).resolve().parent.parent
    paths = sorted(p for d in dirs for p in (root / d).rglob("*") if p.suffix in (".py", ".toml"))
    paths += [root / f for f in files]
    h = hashlib.sha256()
    for f in paths:
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def identity(scene, t_end: float, save_every: float) -> dict:
    """What a reference is: everything that determines its numbers, the code that computes it
    included (``physics``), so that a changed model is never compared with a stale reference."""
    return {"format": FORMAT, "scene": scene.key(), "t_end": float(t_end), "save_every": float(save_every),
            "physics": source_hash(PHYSICS_DIRS), **REFERENCE_METHOD}


def reference_path(scene, t_end: float, save_every: float, cache_dir: Path = CACHE_DIR) -> Path:
    """The file of a reference: one per problem, whatever code computed it (a reference computed
    by other code is found there, refused by its identity and replaced)."""
    key = json.dumps({"scene": scene.key(), "t_end": t_end, "save_every": save_every, **REFERENCE_METHOD}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return Path(cache_dir) / f"reference-{scene.name}-{digest}.npz"


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


def save_reference(traj, path: Path, ident: dict) -> None:
    """Write ``traj`` with its identity and checksum, atomically."""
    from models.io import atomic_path

    arrays = {k: np.asarray(getattr(traj, k)) for k in _ARRAYS if getattr(traj, k) is not None}
    meta = json.dumps({k: getattr(traj, k) for k in ("attitude_kind", "status", "reason", "stats", "integrator",
                                                      "settings", "scene_name")}, default=str, sort_keys=True)
    header = json.dumps({"identity": ident, "versions": _versions(), "meta": meta}, sort_keys=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, header=np.array(header), checksum=np.array(checksum(arrays, header)), **arrays)


class CacheError(ValueError):
    """A cached reference that cannot be trusted (the message says why)."""


def load_reference(path: Path, ident: dict):
    """The trajectory in ``path`` if it loads, is the reference ``ident`` describes and matches
    its checksum; CacheError saying what is wrong otherwise."""
    import zipfile

    if not zipfile.is_zipfile(path):  # an .npz is a zip archive; random bytes, a pickle or a cut file are not
        raise CacheError("cannot be read (not an .npz archive: truncated or not written by reelbench)")
    try:
        with np.load(path, allow_pickle=False) as data:
            files = set(data.files)
            if "header" not in files or "checksum" not in files:
                raise CacheError("no identity or checksum (written by an older version or another program)")
            header = str(data["header"])
            stored = str(data["checksum"])
            arrays = {k: data[k] for k in _ARRAYS if k in files}
    except CacheError:
        raise
    except Exception as exc:  # truncated zip, random bytes, a pickle, a bad member: all mean "unusable"
        raise CacheError(f"cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0][:120] if str(exc) else ''})") from None
    try:
        head = json.loads(header)
        got = head["identity"]
        meta = json.loads(head["meta"])
    except (ValueError, KeyError, TypeError) as exc:
        raise CacheError(f"its header is not valid ({exc})") from None
    if got != ident:
        diff = sorted(k for k in set(got) | set(ident) if got.get(k) != ident.get(k))
        raise CacheError(f"it is a different reference (differs in {', '.join(diff)})")
    if checksum(arrays, header) != stored:
        raise CacheError("its numbers do not match their checksum (the file was changed after it was written)")
    return Trajectory(**{k: arrays.get(k) for k in _ARRAYS}, **meta)


def get_reference(scene, t_end: float, save_every: float, cache_dir: Path = CACHE_DIR, log=_log_stderr):
    """The cached reference for (scene, t_end, save_every), computing it on first use, or when
    the cached file cannot be trusted (reported through ``log`` by file name)."""
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
                       save_every=save_every)
    if not traj.ok:
        raise RuntimeError(f"reference solution for {scene.name} failed: {traj.status}: {traj.reason}")
    save_reference(traj, path, ident)
    return traj
