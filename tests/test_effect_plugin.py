"""A new effect needs no integrator edit: effects registered at run time.

* `tip_spring`, the potential of models/README.md's "Adding an effect" block (run from the
  README itself, so the documentation cannot rot): a linear spring from the body's
  attachment point to a fixed anchor, with its own `[tip_spring]` section;
* `node_drag` (defined here): a linear viscous drag −γ q̇ on every free node, a string force.

Both are registered, loaded from a TOML file, checked like every built-in effect
(tests/test_effects.py), and run by the LGVI, its symmetric variant and a baseline, unchanged.
"""

import re
from pathlib import Path

import numpy as np
import pytest

from reelbench.integrators import get_integrator
from reelbench.models import EFFECTS, SceneError, build_model, load_scene, scene_from_dict
from reelbench.models._jax import jnp
from reelbench.models.diagnostics import evaluate, summary
from reelbench.models.effects import Effect, Key, register_effect, unregister_effect

from test_effects import check_effect

README = Path(__file__).resolve().parent.parent / "models" / "README.md"

#: Scene.key() of every committed scene (cached references and resumed rows are matched by it)
COMMITTED_KEYS = {
    "deployment": "98e6f07213976235", "deployment_to_end": "5c0d1548538ff837", "fast_spin": "d9101989cfb9242b",
    "fixed_length": "d8b1399d44cc4610", "long_horizon": "b7f82563c22f5644", "many_elements": "1f8d9e7edc76387e",
    "near_slack": "4b82eb764f658df4", "reel_reversal": "c8d10cd48e6e25aa", "retrieval": "6510940f027fe9f9",
    "retrieval_to_limit": "d37097e3ad239cdd", "stiff_string": "f2a6e25437806369",
}


def readme_effect():
    """The README's effect class (the python block defining an Effect subclass)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    code = next(b for b in blocks if "(Effect)" in b)
    ns = {}
    exec(compile(code, str(README), "exec"), ns)
    return next(v for v in ns.values() if isinstance(v, type) and issubclass(v, Effect) and v is not Effect)


class NodeDrag(Effect):
    """Linear viscous drag Q_b = −γ q̇_b on the free nodes (air drag, crudely): power −γ Σ|q̇_b|² ≤ 0."""

    name = "node_drag"
    forcing = True
    dissipative = True
    keys = {"node_drag": {"coefficient": Key("float", "nonnegative", required_by=("node_drag",),
                                             only_with_effect=True)}}

    def string_forces(self, model):
        gamma = model.scene.section("node_drag")["coefficient"]

        def Q(t, x, w):
            return model.over_w(dq=-gamma * w[model.layout.nodes])

        return {"Q_node_drag": Q}

    def power(self, model, t, x, w):
        v = w[model.layout.nodes]
        return -model.scene.section("node_drag")["coefficient"] * (v @ v)


class OtherDrag(NodeDrag):
    """The same force under another name (registered and removed inside one test)."""

    name = "other_drag"
    keys = {"other_drag": NodeDrag.keys["node_drag"]}


def test_committed_keys_without_plugins():
    """The same keys with only the built-in effects (this test does not use the fixture)."""
    assert "tip_spring" not in EFFECTS  # runs before the `plugins` fixture registers it
    assert {name: load_scene(name).key() for name in COMMITTED_KEYS} == COMMITTED_KEYS


def test_unregistering_restores_the_registry_and_refuses_the_keys(tmp_path):
    before = list(EFFECTS)
    register_effect(OtherDrag())
    try:
        assert list(EFFECTS) == before + ["other_drag"]
        with pytest.raises(ValueError, match="already registered"):
            register_effect(OtherDrag())
    finally:
        unregister_effect("other_drag")
    assert list(EFFECTS) == before
    with pytest.raises(ValueError, match="built in"):
        unregister_effect("gravity")
    d = load_scene("fixed_length").to_dict()
    d["other_drag"] = {"coefficient": 0.1}
    with pytest.raises(SceneError, match="unknown key 'other_drag'"):
        scene_from_dict(d, source="x.toml")
    d = load_scene("fixed_length").to_dict()
    d["effects"].append("other_drag")
    with pytest.raises(SceneError, match="unknown effect 'other_drag'"):
        scene_from_dict(d, source="x.toml")


@pytest.fixture(scope="module")
def plugins():
    before = list(EFFECTS)
    spring = register_effect(readme_effect()())
    drag = register_effect(NodeDrag())
    yield spring, drag
    unregister_effect("node_drag")
    unregister_effect("tip_spring")
    assert list(EFFECTS) == before  # the registry is what it was


TOML = """
name = "tip_spring_test"
t_end = 1.0
effects = ["gravity", "elasticity", "rigid_body", "tip_spring"{extra}]
[string]
total_length = 40.0
mass_per_length = 0.05
axial_stiffness = 200.0
elements = 3
[body]
mass = 1.0
box = [0.6, 0.4, 0.2]
attachment_to_com = [0.3, 0.2, 0.1]
[reel]
guide_length = 1.0
[initial]
deployed_length = 10.0
direction = [0.7071067811865476, 0.0, 0.7071067811865476]
tip_velocity = [0.0, 2.0, 0.0]
angular_velocity = [1.0, 0.5, 0.0]
[tip_spring]
stiffness = 20.0
anchor = [3.0, 0.0, 9.0]
{drag}
"""


def write_scene(tmp_path, drag=False):
    text = TOML.format(extra=', "node_drag"' if drag else "", drag="[node_drag]\ncoefficient = 0.05" if drag else "")
    path = tmp_path / ("drag.toml" if drag else "spring.toml")
    path.write_text(text)
    return load_scene(path)


def test_registered_effect_owns_its_scene_keys(plugins, tmp_path):
    scene = write_scene(tmp_path)
    assert scene.effects == ("gravity", "elasticity", "rigid_body", "tip_spring")
    assert scene.section("tip_spring") == {"stiffness": 20.0, "anchor": [3.0, 0.0, 9.0]}
    assert scene.with_(stiffness=30.0).section("tip_spring")["stiffness"] == 30.0  # bare-name override
    assert scene.with_(stiffness=30.0) != scene and scene.with_(stiffness=30.0).key() != scene.key()
    d = scene.to_dict()
    d["effects"] = ["gravity", "elasticity", "rigid_body"]
    with pytest.raises(SceneError, match=r"x\.toml: key 'tip_spring\.stiffness' = 20\.0 is only allowed with "
                                         r"effect 'tip_spring' in the list 'effects'"):
        scene_from_dict(d, source="x.toml")
    d["effects"].append("tip_spring")
    del d["tip_spring"]["anchor"]
    with pytest.raises(SceneError, match=r"missing key 'tip_spring\.anchor' \(needed by effect tip_spring\)"):
        scene_from_dict(d, source="x.toml")
    d["tip_spring"].update(anchor=[0, 0, 1], stiffness=1e20)
    with pytest.raises(SceneError, match=r"'tip_spring\.stiffness' = 1e\+20 is implausible"):
        scene_from_dict(d, source="x.toml")


def test_other_scenes_keep_their_keys(plugins):
    for name, key in COMMITTED_KEYS.items():
        assert load_scene(name).key() == key, name
        assert "tip_spring" not in load_scene(name).to_dict()


def test_plugin_terms_are_checked_like_the_builtin_ones(plugins, tmp_path, rng):
    spring = build_model(write_scene(tmp_path))
    assert "V_tip_spring" in spring.potential_terms and not spring.layout.has_work
    assert check_effect(spring, "tip_spring", rng) == 3
    drag = build_model(write_scene(tmp_path, drag=True))
    assert drag.layout.has_work and "Q_node_drag" in drag.string_forces
    assert check_effect(drag, "node_drag", rng) == 3
    # the spring's energy is in E and in the energy scale; gravity's diagnostics are unchanged
    x, R, w = (jnp.asarray(a) for a in spring.initial_state())
    V = float(spring.potential_terms["V_tip_spring"](x, R))
    assert V > 0 and spring.energy_scale() > V


def _tip(scene, tr):
    return tr.x[-1][build_model(scene).layout.nodes][-3:]


@pytest.mark.parametrize("drag", [False, True], ids=["tip_spring", "tip_spring+node_drag"])
def test_integrators_run_the_new_effect_unchanged(plugins, tmp_path, drag):
    """LGVI, LGVI-sym and DOP853 converge to each other and keep E (E − W with the drag)."""
    scene = write_scene(tmp_path, drag=drag)
    T = 1.0
    ref = get_integrator("dop853").solve(scene, t_end=T, rtol=1e-11, atol=1e-12, save_every=0.05)
    assert ref.ok, ref.reason
    df_ref = evaluate(scene, ref)
    s_ref = summary(df_ref, has_work=drag)
    assert s_ref["energy_error"] < 1e-8, s_ref
    # the plugin's potential has its own column: the parts add up to E
    parts = df_ref["kinetic"] + df_ref["V_gravity"] + df_ref["V_elastic"] + df_ref["V_tip_spring"]
    np.testing.assert_allclose(parts, df_ref["energy"], rtol=1e-13, atol=1e-12)
    if drag:
        assert ref.work[-1] < 0  # the drag dissipates
    for name in ("lgvi", "lgvi_sym"):
        errs = []
        for h in (0.004, 0.002):
            tr = get_integrator(name).solve(scene, t_end=T, dt=h, save_every=0.05)
            assert tr.ok, tr.reason
            errs.append(np.linalg.norm(_tip(scene, tr) - _tip(scene, ref)))
            s = summary(evaluate(scene, tr), has_work=drag)
            assert s["energy_error"] < 1e-3 and s["orthogonality_error"] < 1e-13, (name, h, s)
        print(name, "drag" if drag else "", "tip errors", errs)
        # second order (measured ratio 4.2), towards the same solution (2e-4 relative at h = 2 ms)
        assert errs[1] < errs[0] / 3 and errs[1] < 1e-3 * np.linalg.norm(_tip(scene, ref))
