"""A cached reference is used only when it proves what it is: truncated files,
random bytes, another problem's reference and numbers changed after writing are each
reported by file name and recomputed, never used."""

import shutil

import numpy as np
import pytest

from reelbench.benchmark.core import reference
from reelbench.benchmark.core.reference import CacheError, get_reference, load_reference, reference_path
from reelbench.models import load_scene

T_END, SAVE = 0.04, 0.02


@pytest.fixture(scope="module")
def cached(tmp_path_factory):
    """A good cache file of a tiny scene, and the trajectory it holds."""
    d = tmp_path_factory.mktemp("cache")
    scene = load_scene("fixed_length", elements=1)
    traj = get_reference(scene, T_END, SAVE, d, log=None)
    return scene, traj, reference_path(scene, T_END, SAVE, d)


def _damaged(cached, tmp_path, damage):
    scene, traj, good = cached
    path = reference_path(scene, T_END, SAVE, tmp_path)
    shutil.copy(good, path)
    damage(path)
    said = []
    got = get_reference(scene, T_END, SAVE, tmp_path, log=said.append)
    np.testing.assert_array_equal(got.x, traj.x)  # the recomputed reference, not the damaged one
    assert said and said[0].startswith(f"warning: cached reference {path} is not used"), said
    assert any("computing" in s for s in said[1:]), said
    load_reference(path, reference.identity(scene, T_END, SAVE))  # the file was replaced by a good one
    return said[0]


def test_a_good_cache_file_is_used_without_recomputing(cached, monkeypatch):
    scene, traj, path = cached
    monkeypatch.setattr(reference, "get_integrator", lambda *a: pytest.fail("recomputed"))
    said = []
    got = get_reference(scene, T_END, SAVE, path.parent, log=said.append)
    np.testing.assert_array_equal(got.x, traj.x)
    assert said == []


def test_a_truncated_file_is_reported_and_recomputed(cached, tmp_path):
    msg = _damaged(cached, tmp_path, lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]))
    assert "cannot be read" in msg


def test_random_bytes_are_reported_and_recomputed(cached, tmp_path):
    msg = _damaged(cached, tmp_path, lambda p: p.write_bytes(np.random.default_rng(1).bytes(4000)))
    assert "cannot be read" in msg and "pickle" not in msg


def _rewrite(path, change):
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    change(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def test_scaled_positions_with_the_old_checksum_are_refused(cached, tmp_path):
    def scale(a):
        a["x"] = a["x"] * 1.001

    msg = _damaged(cached, tmp_path, lambda p: _rewrite(p, scale))
    assert "do not match their checksum" in msg


def test_another_problems_reference_is_refused(cached, tmp_path):
    scene, _, good = cached

    def relabel(a):  # an identity that says another horizon, with a checksum made for it
        header = str(a["header"]).replace('"t_end": 0.04', '"t_end": 0.06')
        arrays = {k: a[k] for k in ("t", "x", "attitude", "velocity", "work") if k in a}
        a["header"], a["checksum"] = np.array(header), np.array(reference.checksum(arrays, header))

    msg = _damaged(cached, tmp_path, lambda p: _rewrite(p, relabel))
    assert "different reference (differs in t_end)" in msg


def test_a_reference_computed_by_other_model_code_is_recomputed(cached, tmp_path):
    """Same problem, computed before the model or integrator source changed: the file's
    identity holds the source hash, so the new code never compares with a stale reference."""
    import json

    def other_code(a):
        head = json.loads(str(a["header"]))
        head["identity"]["physics"] = "0" * 12
        header = json.dumps(head, sort_keys=True)
        arrays = {k: a[k] for k in ("t", "x", "attitude", "velocity", "work") if k in a}
        a["header"], a["checksum"] = np.array(header), np.array(reference.checksum(arrays, header))

    msg = _damaged(cached, tmp_path, lambda p: _rewrite(p, other_code))
    assert "different reference (differs in physics)" in msg
    assert reference.identity(cached[0], T_END, SAVE)["physics"] == reference.source_hash(reference.PHYSICS_DIRS)


def test_an_old_format_file_without_identity_is_refused(cached, tmp_path):
    scene, traj, _ = cached
    msg = _damaged(cached, tmp_path, lambda p: traj.save(p))  # a plain Trajectory file
    assert "no identity or checksum" in msg


def test_the_file_records_what_it_is(cached):
    import json

    scene, _, path = cached
    with np.load(path) as data:
        head = json.loads(str(data["header"]))
    assert head["identity"] == reference.identity(scene, T_END, SAVE)
    assert head["identity"]["integrator"] == "dop853" and head["identity"]["rtol"] == 1e-12
    assert {"numpy", "scipy", "jax"} <= set(head["versions"])
    with pytest.raises(CacheError):
        load_reference(path, {**reference.identity(scene, T_END, SAVE), "scene": "other"})
