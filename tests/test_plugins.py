"""The integrator registry: decorator and the `reelbench.integrators` entry-point group."""

import sys
import textwrap

import numpy as np
import pytest

from reelbench import integrators
from reelbench.integrators import Capability, Integrator, get_integrator, register
from reelbench.integrators import registry


PLUGIN_MODULE = '''
import numpy as np
from reelbench.integrators import Capability, Integrator, Trajectory
from reelbench.models import build_model


class ExplicitEuler(Integrator):
    """Forward Euler on the model's quaternion ODE: a minimal outside plugin."""

    name = "test_euler"
    capabilities = frozenset({Capability.FIXED_STEP})
    order = 1

    def solve(self, scene, t_end=None, *, dt=None, save_every=None, **options):
        model = build_model(scene)
        lay = model.layout
        t_end = scene.t_end if t_end is None else t_end
        y = model.initial_ode_state()
        n = int(round(t_end / dt))
        ys = [y]
        for k in range(n):
            y = y + dt * np.asarray(model.ode_rhs_jit(k * dt, y))
            ys.append(y)
        ys = np.array(ys)
        return Trajectory(t=np.arange(n + 1) * dt, x=ys[:, lay.y_x], attitude=ys[:, lay.y_quat],
                          attitude_kind="quaternion", velocity=ys[:, lay.y_w], work=np.zeros(n + 1),
                          integrator=self.name, stats={"steps": n})
'''


@pytest.fixture
def plugin_on_path(tmp_path, monkeypatch):
    """An installed-looking distribution declaring an entry point in our group."""
    (tmp_path / "reelbench_test_plugin.py").write_text(PLUGIN_MODULE)
    dist = tmp_path / "reelbench_test_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: reelbench-test-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        textwrap.dedent(
            f"""
            [{integrators.ENTRY_POINT_GROUP}]
            test_euler = reelbench_test_plugin:ExplicitEuler
            test_broken = reelbench_test_plugin:DoesNotExist
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    yield
    registry.unregister("test_euler")
    registry.unregister("test_broken")
    sys.modules.pop("reelbench_test_plugin", None)


def test_entry_point_plugin_is_discovered_and_integrates_to_first_order(plugin_on_path):
    from reelbench.models import load_scene
    from reelbench.models.diagnostics import evaluate

    from _helpers import reference_solution

    assert "test_euler" in integrators.available()
    integ = get_integrator("test_euler")
    assert integ.has(Capability.FIXED_STEP) and not integ.has(Capability.ADAPTIVE)
    scene = load_scene("fixed_length", elements=2)
    traj = integ.solve(scene, t_end=0.01, dt=0.001)
    df = evaluate(scene, traj)
    assert len(df) == 11 and np.all(np.isfinite(df["energy"]))
    # the plugin's output is the model's solution: forward Euler's error against DOP853 halves with dt
    ref = reference_solution(scene, 0.01, n_save=2)
    errs = [np.abs(integ.solve(scene, t_end=0.01, dt=dt).x[-1] - ref.x[-1]).max() for dt in (0.001, 0.0005)]
    print("forward Euler errors", errs)
    assert 1.7 < errs[0] / errs[1] < 2.3, errs  # order 1 (measured 6.1e-5, 3.1e-5: ratio 2.00)
    # a broken plugin is reported, not fatal
    assert "test_broken" in integrators.plugin_errors()
    with pytest.raises(ValueError, match="failed to load"):
        get_integrator("test_broken")


def test_decorator_registration_and_errors():
    @register
    class Dummy(Integrator):
        name = "test_dummy"
        capabilities = frozenset({Capability.ADAPTIVE})

        def solve(self, scene, t_end=None, **kw):
            raise NotImplementedError

    try:
        assert isinstance(get_integrator("test_dummy"), Dummy)
        with pytest.raises(ValueError, match="taken"):
            @register
            class Other(Dummy):
                name = "test_dummy"
    finally:
        registry.unregister("test_dummy")
    with pytest.raises(ValueError, match="unknown integrator 'test_dumy'"):
        get_integrator("test_dumy")
    with pytest.raises(TypeError):
        register(object)
