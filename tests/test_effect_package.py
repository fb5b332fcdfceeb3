"""An effect shipped by an outside package, through the entry-point group `reelbench.effects`.

A temporary package on disk (`reelbench_tip_force`, with its own dist-info and entry points)
declares three effects: `tip_force` (a constant force on the body's attachment point, a
potential with its closed-form gradient), `broken_effect` (an entry point that does not load)
and `heavier_body` (overrides the kinetic energy, which the closed form and the LGVI would
ignore). The first is found the first time a scene lists it, checked like every built-in
effect and run by ``python -m benchmark run`` (spawned workers included; ``--horizon 0``
leaves out the energy study of fixed_length, which does not involve the plugin); the other
two are reported, not fatal, and a scene that lists one is refused with the reason.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from reelbench.integrators import get_integrator
from reelbench.models import EFFECTS, SceneError, build_model, load_scene, scene_from_dict
from reelbench.models import effects as effect_registry
from reelbench.models.effects import ENTRY_POINT_GROUP, unregister_effect

from test_effects import check_effect
from test_scene_input import scene_text

ROOT = Path(__file__).resolve().parent.parent

PLUGIN = textwrap.dedent('''
    """A constant force F on the body's attachment point (wind on the body, say)."""
    import numpy as np

    from reelbench.models.effects import Effect, Key, PotentialTerm


    class TipForce(Effect):
        """V = -F . (r_p + q_{N+1}): the work of a constant force at the last node."""

        name = "tip_force"
        summary = "a constant force on the body's attachment point"
        keys = {"tip_force": {"force": Key("vec3", required_by=("tip_force",), only_with_effect=True)}}
        plausible = {"tip_force.force": (0.0, 1e6)}

        def potentials(self, model):
            from reelbench.models._jax import jnp

            F = jnp.asarray(model.scene.section("tip_force")["force"])

            def V(x, R):
                return -F @ (model.r_p + model.nodes(x)[-1])

            def dV(x, R):
                return model.over_w(dq=jnp.zeros((model.N, 3)).at[-1].set(-F))

            return {"V_tip_force": PotentialTerm(V, dV)}

        def energy_scale(self, model):
            # the most work F can do as the attachment point moves over the string's reach and back
            return float(np.linalg.norm(model.scene.section("tip_force")["force"])) * 2.0 * model.L


    class HeavierBody(Effect):
        name = "heavier_body"

        def kinetic(self, model):
            return {"T_extra": lambda x, R, w: 0.5 * (w @ w)}
''')

ENTRY_POINTS = f"""[{ENTRY_POINT_GROUP}]
tip_force = reelbench_tip_force:TipForce
heavier_body = reelbench_tip_force:HeavierBody
broken_effect = reelbench_tip_force:NoSuchClass
"""

#: fixed_length with 3 elements and the force on its body
SCENE = scene_text("fixed_length", name='name = "tip_force_scene"', elements="elements = 3",
                   effects='effects = ["gravity", "elasticity", "rigid_body", "tip_force"]') + """
[tip_force]
force = [3.0, -2.0, 0.0]
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A site directory holding the package as an installed-looking distribution, and a scene using it."""
    site = tmp_path_factory.mktemp("site")
    (site / "reelbench_tip_force.py").write_text(PLUGIN)
    dist = site / "reelbench_tip_force-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: reelbench-tip-force\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(ENTRY_POINTS)
    (site / "tip_force_scene.toml").write_text(SCENE)
    return site


@pytest.fixture(scope="module")
def installed(site):
    """The package on the path for this module's tests; its effects unregistered afterwards."""
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(site))
        yield site
    for name in ("tip_force", "heavier_body", "broken_effect"):
        if name in EFFECTS or name in effect_registry._PLUGIN_ERRORS:
            unregister_effect(name)
    sys.modules.pop("reelbench_tip_force", None)


@pytest.fixture(scope="module")
def swings(installed):
    """The scene's first 0.2 s by the LGVI in this process, with the force and without it."""
    scene = load_scene(installed / "tip_force_scene.toml")
    plain = scene.with_(effects=["gravity", "elasticity", "rigid_body"])
    return scene, plain, [get_integrator("lgvi").solve(s, t_end=0.2, dt=0.0025, save_every=0.02) for s in (scene, plain)]


def test_the_plugin_is_loaded_when_a_scene_lists_it_and_broken_ones_are_reported(installed):
    assert "tip_force" not in EFFECTS  # nothing imported it: it is found through its entry point
    scene = load_scene(installed / "tip_force_scene.toml")
    assert scene.effects[-1] == "tip_force" and scene.section("tip_force") == {"force": [3.0, -2.0, 0.0]}
    errors = effect_registry.plugin_errors()
    assert "AttributeError" in errors["broken_effect"] and "NoSuchClass" in errors["broken_effect"]
    assert "Effect.kinetic" in errors["heavier_body"] and "LGVI" in errors["heavier_body"]
    assert "heavier_body" not in EFFECTS and "broken_effect" not in EFFECTS
    d = scene.to_dict()
    for name, reason in (("heavier_body", "the closed form"), ("broken_effect", "failed to load")):
        bad = dict(d, effects=d["effects"] + [name])
        refusal = rf"x\.toml: key 'effects' lists '{name}', which cannot be used: .*{reason}"
        with pytest.raises(SceneError, match=refusal):
            scene_from_dict(bad, source="x.toml")


def test_the_plugin_effect_is_checked_like_the_builtin_ones(swings, rng):
    scene, plain, (pushed, free) = swings
    model = build_model(scene)
    assert model.terms_of("tip_force") == ("V_tip_force",)
    assert check_effect(model, "tip_force", rng) == 3
    assert "tip_force" not in plain.to_dict() and plain.key() != scene.key()
    # the force acts: the same start without it swings differently (5 cm apart at 0.2 s)
    assert pushed.ok and free.ok
    assert np.abs(pushed.x[-1] - free.x[-1]).max() > 1e-2


def test_benchmark_run_uses_the_plugin_effect_in_its_workers(installed, swings, tmp_path):
    """The exact command of a user who installed the package: the scene is validated by the
    command line, its runs and its reference are computed in a spawned worker process (`--jobs 1`:
    one pool worker, so one compile of each method)."""
    out = tmp_path / "out"
    cache = tmp_path / "cache"  # the user's cache, where every study keeps its references
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(installed)]), REELBENCH_CACHE=str(cache))
    cmd = [sys.executable, "-m", "benchmark", "run", "--scenes", str(installed / "tip_force_scene.toml"),
           "--integrators", "lgvi,dop853", "--quick", "--horizon", "0", "--jobs", "1", "--out", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = pd.read_csv(out / "runs.csv")
    assert set(runs["scene"]) == {"tip_force_scene"}
    assert set(runs["integrator"]) == {"lgvi", "dop853"}
    assert (runs["status"] == "ok").all(), runs[["integrator", "status", "reason"]]
    assert (runs["position_error_final"] > 0).all() and np.isfinite(runs["position_error_final"]).all()
    # the workers ran the plugin's physics: their reference is this process's LGVI solution with the
    # force (to its error at dt = 2.5 ms), not the one without it
    scene, plain, (pushed, free) = swings
    [ref_file] = (cache / "references").glob("reference-tip_force_scene-*.npz")
    ref = np.load(ref_file)
    at = int(np.argmin(np.abs(ref["t"] - pushed.t[-1])))
    assert abs(ref["t"][at] - 0.2) < 1e-12
    tip = slice(-3, None)
    assert np.abs(ref["x"][at][tip] - pushed.x[-1][tip]).max() < 1e-4
    assert np.abs(ref["x"][at][tip] - free.x[-1][tip]).max() > 1e-2

    listing = subprocess.run([sys.executable, "-m", "benchmark", "list"], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=300)
    assert listing.returncode == 0, listing.stderr[-2000:]
    assert "tip_force" in listing.stdout.split("effects:")[1]
    assert "broken_effect" in listing.stdout and "FAILED TO LOAD" in listing.stdout
