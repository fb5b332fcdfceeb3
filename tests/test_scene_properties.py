"""Bad input beyond the shipped scenes, property-based with hypothesis.

Every generated scene value is either refused with a `SceneError` naming the key, or accepted
and then simulated (a short LGVI run: one compile per example, so 2 examples in the fast suite,
40 in the ``slow`` one) with every
saved state and diagnostic finite, or stopped with a named status.
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from reelbench.integrators import Status, get_integrator
from reelbench.models import SceneError, load_scene, scene_from_dict
from reelbench.models.diagnostics import evaluate

BASE = load_scene("retrieval").to_dict()
NAMED = {s.value for s in Status} - {"ok"}

FAST = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SIM = settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.too_slow])

non_finite = st.sampled_from([math.nan, math.inf, -math.inf])
not_a_number = st.one_of(st.text(max_size=3), st.booleans(), st.lists(st.floats(), max_size=2))
non_positive = st.one_of(st.floats(max_value=0.0, allow_nan=False), st.integers(max_value=0))
negative = st.one_of(st.floats(max_value=0.0, exclude_max=True, allow_nan=False), st.integers(max_value=-1))

#: (dotted key, strategy of values that break that key's own rule)
POSITIVE_KEYS = ["t_end", "string.total_length", "string.mass_per_length", "string.axial_stiffness", "body.mass",
                 "reel.radius", "reel.guide_length", "reel.equivalent_mass", "initial.deployed_length"]


def _with(key, value, base=BASE):
    d = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    if "." in key:
        sec, k = key.split(".")
        d[sec][k] = value
    else:
        d[key] = value
    return d


def _refused_naming(key, value):
    with pytest.raises(SceneError) as exc:
        scene_from_dict(_with(key, value), source="generated.toml")
    msg = str(exc.value)
    assert f"'{key}'" in msg and "generated.toml" in msg and "allowed" in msg, msg
    return msg


@FAST
@given(key=st.sampled_from(POSITIVE_KEYS), value=st.one_of(non_positive, non_finite, not_a_number))
def test_non_positive_or_non_finite_numbers_are_refused(key, value):
    _refused_naming(key, value)


@FAST
@given(value=st.one_of(st.integers(max_value=0), st.floats(allow_nan=True).filter(lambda v: not (v >= 1 and float(v).is_integer())),
                       not_a_number))
def test_bad_element_counts_are_refused(value):
    _refused_naming("string.elements", value)


@FAST
@given(value=st.one_of(st.floats(min_value=39.0, allow_infinity=True, allow_nan=False), non_finite))
def test_deployed_length_outside_its_range_is_refused(value):
    _refused_naming("initial.deployed_length", value)  # L - b = 39 m


@FAST
@given(value=st.one_of(st.floats(max_value=0.01, exclude_max=True), st.floats(min_value=100.0, exclude_min=True),
                       non_finite, not_a_number))
def test_stretch_outside_its_range_is_refused(value):
    _refused_naming("initial.stretch", value)


@FAST
@given(value=st.one_of(negative, st.floats(min_value=15.0), non_finite))
def test_min_deployed_length_outside_its_range_is_refused(value):
    _refused_naming("reel.min_deployed_length", value)  # initial deployed length 15 m


@FAST
@given(key=st.sampled_from(["initial.direction", "reel.exit_direction", "initial.tip_velocity",
                            "initial.angular_velocity", "body.attachment_to_com", "reel.center", "body.box"]),
       bad=st.integers(0, 2), value=non_finite)
def test_vectors_with_a_non_finite_entry_are_refused(key, bad, value):
    vec = [0.3, 0.2, 0.1]
    vec[bad] = value
    _refused_naming(key, vec)


@FAST
@given(m=st.lists(st.floats(-2, 2, allow_nan=False), min_size=9, max_size=9))
def test_attitude_is_refused_unless_a_rotation(m):
    R = np.array(m).reshape(3, 3)
    is_rotation = np.abs(R.T @ R - np.eye(3)).max() <= 1e-9 and abs(np.linalg.det(R) - 1) <= 1e-9
    d = _with("initial.attitude", R.tolist())
    if is_rotation:  # pragma: no cover - a random matrix is almost never one
        scene_from_dict(d)
    else:
        _refused_naming("initial.attitude", R.tolist())


@FAST
@given(q=st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4), eps=st.floats(1e-6, 0.1))
def test_nearly_orthonormal_attitudes_are_refused(q, eps):
    q = np.array(q)
    assume(np.linalg.norm(q) > 0.1)
    w, x, y, z = q / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    scene_from_dict(_with("initial.attitude", R.tolist()))  # a rotation is accepted
    _refused_naming("initial.attitude", (R * (1 + eps)).tolist())


# ------------------------------------------------------------------------------------------
# Extreme but valid values: simulated, with finite results or a named status
# ------------------------------------------------------------------------------------------
def _log_uniform(lo, hi):
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: 10.0 ** e)


extreme_values = dict(EA=_log_uniform(1e-2, 1e8), mu=_log_uniform(1e-4, 1e2), m=_log_uniform(1e-3, 1e4),
                      stretch=_log_uniform(0.05, 20.0), omega=st.floats(-300, 300), tip=st.floats(-100, 100),
                      elements=st.integers(1, 3), ell=st.floats(0.05, 38.0))


@SIM
@given(**extreme_values)
def test_extreme_valid_scenes_simulate_finitely_or_stop_with_a_status(EA, mu, m, stretch, omega, tip, elements, ell):
    _simulate_extreme(EA, mu, m, stretch, omega, tip, elements, ell)


@pytest.mark.slow
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(**extreme_values)
def test_many_extreme_valid_scenes_simulate_finitely_or_stop_with_a_status(EA, mu, m, stretch, omega, tip, elements, ell):
    _simulate_extreme(EA, mu, m, stretch, omega, tip, elements, ell)


def _simulate_extreme(EA, mu, m, stretch, omega, tip, elements, ell):
    scene = load_scene("fixed_length", axial_stiffness=EA, mass_per_length=mu, mass=m, stretch=stretch,
                       angular_velocity=[omega, 0.3, -0.2], tip_velocity=[0.0, tip, 0.0], elements=elements,
                       deployed_length=ell)
    tr = get_integrator("lgvi").solve(scene, t_end=0.02, dt=1e-3, save_every=1e-3)
    assert tr.status == "ok" or (tr.status in NAMED and tr.reason)
    for a in (tr.t, tr.x, tr.velocity, tr.work, tr.attitude, tr.momentum):
        assert np.all(np.isfinite(a))
    df = evaluate(scene, tr)
    assert np.all(np.isfinite(df.to_numpy(dtype=float)))
