"""Scene loading and validation: every rule of models/README.md refuses bad input with a clear message."""

import tomllib

import numpy as np
import pytest

from reelbench.models import EFFECTS, SceneError, available_scenes, load_scene, scene_from_dict
from reelbench.models.scene import SCENE_DIR


def base_dict(name="retrieval"):
    with open(SCENE_DIR / f"{name}.toml", "rb") as fh:
        return tomllib.load(fh)


def test_shipped_scenes_load_with_paper_values():
    assert {"fixed_length", "deployment", "retrieval"} <= set(available_scenes())
    fixed = load_scene("fixed_length")
    assert fixed.effects == ("gravity", "elasticity", "rigid_body")
    assert fixed.string.elements == 10 and fixed.string.total_length == 40.0
    assert fixed.initial.deployed_length == 10.0
    np.testing.assert_allclose(fixed.inertia, np.diag([1 / 12 * (0.16 + 0.04), 1 / 12 * (0.36 + 0.04), 1 / 12 * (0.36 + 0.16)]))
    dep = load_scene("deployment")
    assert dep.has("reel") and dep.has("carnot") and not dep.has("reel_control")
    ret = load_scene("retrieval")
    assert ret.reel.control_moment == 11.0 and ret.initial.deployed_length == 15.0


def test_load_by_path_and_overrides():
    s = load_scene(SCENE_DIR / "fixed_length.toml", elements=40, t_end=2.0)
    assert s.string.elements == 40 and s.t_end == 2.0
    s2 = load_scene("fixed_length", **{"string.axial_stiffness": 2000.0})
    assert s2.string.axial_stiffness == 2000.0
    assert s2.key() != load_scene("fixed_length").key()
    assert load_scene("fixed_length").key() == load_scene("fixed_length").key()
    # inertia override replaces the box
    s3 = load_scene("fixed_length", inertia=[[1, 0, 0], [0, 2, 0], [0, 0, 2.5]])
    np.testing.assert_allclose(s3.inertia, np.diag([1, 2, 2.5]))
    # direction normalised on load
    s4 = load_scene("fixed_length", direction=[0, 0, 2.0])
    assert s4.initial.direction == (0.0, 0.0, 1.0)


def test_scene_round_trip_and_with():
    s = load_scene("deployment")
    again = scene_from_dict(s.to_dict())
    assert again == s
    assert s.with_(elements=5).string.elements == 5


def test_with_accepts_a_scene_whose_file_has_no_reel_table():
    """A fixed-length file without [reel] gets the reel keys' defaults (guide_length = 0, which a
    reel scene would refuse): `with_` re-validates what `to_dict` writes back, and must accept it."""
    d = load_scene("fixed_length").to_dict()
    del d["reel"]
    s = scene_from_dict(d)
    assert s.reel.guide_length == 0.0
    assert s.with_(elements=5).string.elements == 5 and s.with_(elements=5).reel == s.reel
    # with a reel, an explicit 0 is still refused
    dep = load_scene("deployment").to_dict()
    dep["reel"]["guide_length"] = 0.0
    with pytest.raises(SceneError, match="guide_length"):
        scene_from_dict(dep)


@pytest.mark.parametrize(
    "mutate, fragments",
    [
        (lambda d: d["string"].update(elements=0), ["string.elements", "integer >= 1"]),
        (lambda d: d["string"].update(elements=2.5), ["string.elements", "integer >= 1"]),
        (lambda d: d["string"].update(total_length=-1.0), ["string.total_length", "> 0"]),
        (lambda d: d["string"].update(mass_per_length=0.0), ["string.mass_per_length", "> 0"]),
        (lambda d: d["string"].update(axial_stiffness=float("nan")), ["string.axial_stiffness", "> 0"]),
        (lambda d: d["body"].update(mass=float("inf")), ["body.mass", "> 0"]),
        (lambda d: d["body"].update(box=[0.6, -0.4, 0.2]), ["body.box", "> 0"]),
        (lambda d: d["reel"].update(radius=0.0), ["reel.radius", "> 0"]),
        (lambda d: d["reel"].update(equivalent_mass=-15.0), ["reel.equivalent_mass", "> 0"]),
        (lambda d: d["reel"].update(guide_length=0.0), ["reel.guide_length", "> 0"]),
        (lambda d: d["reel"].update(control_moment=float("nan")), ["reel.control_moment", "finite"]),
        (lambda d: d.update(t_end=0.0), ["t_end", "> 0"]),
        (lambda d: d["initial"].update(deployed_length=0.0), ["initial.deployed_length", "> 0"]),
        (lambda d: d["initial"].update(deployed_length=39.5), ["initial.deployed_length", "total_length - guide_length"]),
        (lambda d: d["initial"].update(direction=[0, 0, 0]), ["initial.direction", "nonzero"]),
        (lambda d: d["reel"].update(exit_direction=[0, 0, 0]), ["reel.exit_direction", "nonzero"]),
        (lambda d: d["initial"].update(tip_velocity=[0, 1]), ["initial.tip_velocity", "3 finite numbers"]),
        (lambda d: d["initial"].update(attitude=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), ["initial.attitude", "det +1"]),
        (lambda d: d["initial"].update(attitude=[[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]), ["initial.attitude", "orthonormal"]),
        (lambda d: d["body"].update(inertia=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), ["body.box", "body.inertia", "alternatives"]),
        (lambda d: (d["body"].pop("box"), d["body"].update(inertia=[[1, 0, 0], [0, -1, 0], [0, 0, 1]])), ["body.inertia", "positive-definite"]),
        (lambda d: d["body"].pop("box"), ["body.box", "rigid_body"]),
        (lambda d: d["environment"].update(g=-9.81), ["environment.g", ">= 0"]),
        (lambda d: d.update(effects=["gravity", "elasticity", "rigid_body", "carnot"]), ["carnot", "needs effect 'reel'"]),
        (lambda d: d.update(effects=["gravity", "elasticity", "reel_control"]), ["reel_control", "needs effect 'reel'"]),
        (lambda d: d.update(effects=["gravity", "reel"]), ["effects", "elasticity"]),
        (lambda d: d.update(effects=["gravity", "elasticity", "gravity"]), ["effects", "once"]),
        (lambda d: d.update(effects=["gravty", "elasticity"]), ["gravty", "did you mean 'gravity'"]),
        (lambda d: d["string"].update(element=3), ["string.element", "did you mean 'elements'"]),
        (lambda d: d.update(t_ned=3.0), ["t_ned", "did you mean 't_end'"]),
        (lambda d: d["initial"].pop("deployed_length"), ["initial.deployed_length", "missing"]),
        (lambda d: d["reel"].pop("radius"), ["reel.radius", "missing", "reel"]),
        # a key of an effect not listed, with a value other than its default, would be ignored: refused
        (lambda d: d.update(effects=["gravity", "elasticity", "rigid_body"]),
         ["reel.control_moment", "= 11.0", "only used with effect 'reel_control'", "add 'reel_control' to 'effects'"]),
        (lambda d: d.update(effects=["gravity", "elasticity", "rigid_body", "reel"]),
         ["reel.control_moment", "only used with effect 'reel_control'"]),
        (lambda d: (d.update(effects=["gravity", "elasticity"]), d["body"].pop("box"), d["body"].pop("attachment_to_com")),
         ["initial.angular_velocity", "only used with effect 'rigid_body'", "its default, [0.0, 0.0, 0.0]"]),
        (lambda d: d.update(effects=["gravity", "elasticity"]), ["body.box", "only used with effect 'rigid_body'"]),
        (lambda d: (d.update(effects=["gravity", "elasticity", "rigid_body"]), d["reel"].update(control_moment=0.0),
                    d["initial"].update(reel_rate=1.0)), ["initial.reel_rate", "only used with effect 'reel'"]),
        (lambda d: d["string"].update(elements=True), ["string.elements"]),
        (lambda d: d.update(string=3), ["string", "table"]),
    ],
)
def test_invalid_scene_is_refused_with_file_key_and_range(mutate, fragments, tmp_path):
    d = base_dict("retrieval" if not {"initial.angular_velocity", "body.box"} & set(fragments) else "fixed_length")
    mutate(d)
    assert_refused(d, fragments)


def assert_refused(d, fragments):
    """Loading ``d`` raises a SceneError naming the file and every fragment (key, allowed range)."""
    with pytest.raises(SceneError) as err:
        scene_from_dict(d, source="bad_scene.toml")
    msg = str(err.value)
    assert "bad_scene.toml" in msg
    for frag in fragments:
        assert frag in msg, msg


def test_unknown_scene_name_and_override_suggest():
    with pytest.raises(SceneError, match="did you mean 'fixed_length'"):
        load_scene("fixed_lenght")
    with pytest.raises(SceneError, match="did you mean 'elements'"):
        load_scene("fixed_length", elemnts=3)
    with pytest.raises(SceneError, match="string.elements"):
        load_scene("fixed_length", elements=-2)


def test_bad_toml_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("name = \n")
    with pytest.raises(SceneError, match="broken.toml"):
        load_scene(p)


def test_every_effect_is_known_and_dependencies_closed():
    for eff, effect in EFFECTS.items():
        assert effect.name == eff and all(n in EFFECTS for n in effect.needs)
