"""Reference solutions: computed once per scene at tight tolerance, cached, reused.

The cache key is a hash of the scene (its physics, not its name), the horizon, the save
interval and the reference method's settings, so a changed scene never reuses a stale file.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from integrators import Trajectory, get_integrator

REFERENCE_METHOD = {"integrator": "dop853", "rtol": 1e-12, "atol": 1e-14}
CACHE_DIR = Path("results") / "cache"


def reference_path(scene, t_end: float, save_every: float, cache_dir: Path = CACHE_DIR) -> Path:
    key = json.dumps({"scene": scene.key(), "t_end": t_end, "save_every": save_every, **REFERENCE_METHOD}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return Path(cache_dir) / f"reference-{scene.name}-{digest}.npz"


def get_reference(scene, t_end: float, save_every: float, cache_dir: Path = CACHE_DIR, log=None) -> Trajectory:
    """The cached reference for (scene, t_end, save_every), computing it on first use."""
    path = reference_path(scene, t_end, save_every, cache_dir)
    if path.exists():
        return Trajectory.load(path)
    if log:
        log(f"reference: computing {scene.name} to t = {t_end:g} s with {REFERENCE_METHOD} ...")
    integ = get_integrator(REFERENCE_METHOD["integrator"])
    traj = integ.solve(scene, t_end=t_end, rtol=REFERENCE_METHOD["rtol"], atol=REFERENCE_METHOD["atol"],
                       save_every=save_every)
    if not traj.ok:
        raise RuntimeError(f"reference solution for {scene.name} failed: {traj.status}: {traj.reason}")
    traj.save(path)
    return traj
