"""Cross-validation against MoorDyn and MuJoCo (benchmark/studies/xval.py): the translation of a scene,
the same discrete model in three codes, and the refusal of what cannot be translated."""

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

from reelbench.benchmark.studies import xval
from reelbench.benchmark.studies import xval_moordyn, xval_mujoco, xval_report
from reelbench.benchmark.core.report import Provenance
from reelbench.benchmark.cli.main import main as cli_main
from reelbench.models import build_model, load_scene

TIMES = np.linspace(0.0, 0.5, 11)
DT = 1e-4  # RK4 at N = 5 (ω_max = 63 rad/s): time error far below 1e-8 m over 0.5 s


@pytest.fixture(scope="module")
def body_scene():
    return load_scene("fixed_length", elements=5, mass_model="lumped", t_end=0.5)


@pytest.fixture(scope="module")
def point_scene(body_scene):
    return xval.case_scene(body_scene, "point_mass")


# ------------------------------------------------------------------------------------------
# Same discrete model in three codes
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")  # the references of the module


def test_lumped_point_mass_equals_moordyn_and_mujoco(point_scene, tmp_path, cache):
    ours = xval.run_ours(point_scene, TIMES, cache)
    md = xval.run_moordyn(point_scene, TIMES, DT, workdir=tmp_path)
    mj = xval.run_mujoco(point_scene, TIMES, DT)
    # the tip moves by metres over 0.5 s: equal positions are not a trivial agreement
    assert np.linalg.norm(ours.tip[-1] - ours.tip[0]) > 0.5
    print("point mass: |ours - moordyn|", np.abs(ours.tip - md.tip).max(), "|ours - mujoco|", np.abs(ours.tip - mj.tip).max())
    assert np.max(np.linalg.norm(ours.tip - md.tip, axis=1)) <= 1e-8  # measured 1.2e-13
    assert np.max(np.linalg.norm(ours.tip - mj.tip, axis=1)) <= 1e-8  # measured 1.1e-13
    # the consistent model is a different discrete model: far from the lumped one at N = 5
    cons = xval.run_ours(point_scene.with_(mass_model="consistent"), TIMES, cache)
    assert np.max(np.linalg.norm(cons.tip - md.tip, axis=1)) > 1e-4


def test_lumped_in_water_equals_moordyn(point_scene, tmp_path, cache):
    """Buoyancy and Morison drag (normal 1.3, tangential 0.02, a point with volume and C_d A):
    the same discrete model as MoorDyn's line, to 1e-9 m over 0.5 s; the water moves the tip by
    far more than that (the issue's 0.54 m)."""
    wet = xval.case_scene(point_scene, "in_water")
    assert {"buoyancy", "drag"} <= set(wet.effects) and wet.string.mass_model == "lumped"
    ours = xval.run_ours(wet, TIMES, cache)
    md = xval.run_moordyn(wet, TIMES, DT, workdir=tmp_path)
    dry = xval.run_ours(point_scene, TIMES, cache)
    print("in water: |ours - moordyn|", np.abs(ours.tip - md.tip).max(), "|wet - dry|", np.abs(ours.tip - dry.tip).max())
    assert np.max(np.linalg.norm(ours.tip - md.tip, axis=1)) <= 1e-9  # measured 4.0e-13
    assert np.max(np.linalg.norm(ours.tip - dry.tip, axis=1)) > 0.5


def test_study_in_water_same_model_to_1e9_at_equal_n(point_scene):
    """The study's own equal-N comparison (`xval.compute`, its tables): our lumped model's DOP853
    solution vs MoorDyn at the study's dt, in water, at N = 5 over 0.5 s, is at most 1e-9 m, and so
    is MoorDyn's time error (its dt vs dt/2); the LGVI rows are the LGVI's time error, not the model's."""
    study = xval.compute(point_scene, elements=(5,), t_end=0.5, cases=["in_water"], log=lambda msg: None)
    runs = study.runs[("in_water", 5)]
    assert set(runs) == {"ours_consistent", "ours_lumped", xval.REFERENCE_CODE, "moordyn", "moordyn_half_dt"}
    assert runs["moordyn_half_dt"].dt == pytest.approx(runs["moordyn"].dt / 2)
    diff = xval_report.tables(study).differences.set_index("pair")
    same = diff.loc[f"{xval.REFERENCE_CODE} - moordyn"]
    print("in water, study at N = 5:", diff.max_tip_distance_m.to_dict())
    assert same.measures == xval_report.SAME_MODEL and "DOP853" in same.compared and "RK4" in same.compared
    assert same.max_tip_distance_m <= xval.MODEL_TOLERANCE == 1e-9  # measured 1.8e-11
    assert diff.loc["moordyn - moordyn_half_dt"].max_tip_distance_m <= 1e-9  # measured 1.7e-11
    assert np.linalg.norm(runs["moordyn"].tip[-1] - runs["moordyn"].tip[0]) > 0.3  # the tip moves (0.35 m)


def test_in_water_consistent_and_lumped_converge_to_one_limit(point_scene, cache):
    """The finite-element string (Gauss quadrature of the distributed drag) and the lumped one
    (MoorDyn's nodes) approach each other as N grows (in vacuum their self-convergence orders are
    1.4 to 1.9 at these N, results/xval/self_convergence.csv)."""
    wet = xval.case_scene(point_scene, "in_water")
    gap = {}
    for N in (4, 8, 16):
        tips = [xval.run_ours(wet.with_(elements=N, mass_model=m), TIMES, cache).tip for m in ("consistent", "lumped")]
        gap[N] = np.max(np.linalg.norm(tips[0] - tips[1], axis=1))
    print("in water: |consistent - lumped| by N", gap)
    # measured 0.028, 0.014, 0.0058 m: halved and more with each doubling of N
    assert gap[16] < gap[8] < gap[4] and gap[16] < gap[4] / 3


def test_moordyn_input_in_water(point_scene):
    text = xval.moordyn_input(xval.case_scene(point_scene, "in_water"), 2e-4)
    line_type = next(line for line in text.splitlines() if line.startswith("string "))
    # diameter, mass/length, EA, BA, EI, Cd = C_n, Ca = 0 (no added mass), CdAx = C_t, CaAx = 0
    assert line_type.split()[1:] == ["0.0070000000000000001", "0.050000000000000003", "200", "0.0", "0.0", "1.3", "0.0",
                                     "0.02", "0.0"]
    free = next(line for line in text.splitlines() if " Free " in line).split()
    assert [float(v) for v in free[6:]] == [xval.WATER["body.volume"], xval.WATER["body.drag_area"], 0.0]
    assert float(free[4]) < -xval.SUBMERGED + 1e-9  # below the surface, wholly submerged
    assert any(line.split()[:2] == ["1025", "WtrDnsty"] for line in text.splitlines())


def test_fluid_is_moordyns_only_and_without_a_current(point_scene):
    wet = xval.case_scene(point_scene, "in_water")
    with pytest.raises(xval.Untranslatable, match="mujoco cannot translate.*effect 'buoyancy'.*Morison"):
        xval.mujoco_xml(wet, 1e-4)
    with pytest.raises(xval.Untranslatable, match="a current"):
        xval.moordyn_input(wet.with_(**{"fluid.current": [0.5, 0.0, 0.0]}), 1e-4)


def test_lumped_rigid_body_equals_mujoco(body_scene, cache):
    ours = xval.run_ours(body_scene, TIMES, cache)
    mj = xval.run_mujoco(body_scene, TIMES, DT)
    print("rigid body: |ours - mujoco|", np.abs(ours.tip - mj.tip).max())
    assert np.max(np.linalg.norm(ours.tip - mj.tip, axis=1)) <= 1e-8  # measured 4.3e-13
    # without the body's inertia (a point mass) the tip goes elsewhere: the body is really there
    pm = xval.run_ours(xval.case_scene(body_scene, "point_mass"), TIMES, cache)
    assert np.max(np.linalg.norm(pm.tip - mj.tip, axis=1)) > 1e-3


# ------------------------------------------------------------------------------------------
# Translation
# ------------------------------------------------------------------------------------------
def test_moordyn_input_settings(point_scene):
    text = xval.moordyn_input(point_scene, 2e-4)
    rows = {line.split()[1]: line.split()[0] for line in text.splitlines()
            if len(line.split()) >= 2 and line.split()[1] in ("dtM", "tScheme", "g", "WtrDnsty", "WtrDpth", "TmaxIC")}
    assert rows == {"dtM": "0.00020000000000000001", "tScheme": "RK4", "g": "9.8100000000000005",
                    "WtrDnsty": "0.0", "WtrDpth": "10000", "TmaxIC": "0.0"}
    line_type = next(line for line in text.splitlines() if line.startswith("string "))
    # mass/length, EA, then BA, EI, Cd, Ca, CdAx, CaAx all zero
    assert line_type.split()[2:] == ["0.050000000000000003", "200", "0.0", "0.0", "0.0", "0.0", "0.0", "0.0"]
    free = next(line for line in text.splitlines() if " Free " in line).split()
    tip = build_model(point_scene).initial_state()[0][-3:]
    # MoorDyn's z is up (ours e3 down): ours (x, y, z) -> (x, -y, -z); mass m_b, no volume/drag
    np.testing.assert_allclose([float(v) for v in free[2:5]], [tip[0], -tip[1], -tip[2]], rtol=1e-15)
    assert float(free[2 + 3]) == point_scene.body.mass and [float(v) for v in free[6:]] == [0.0, 0.0, 0.0]
    assert next(line for line in text.splitlines() if line.startswith("1    string")).split()[4:6] == ["10", "5"]


def test_mujoco_xml_masses_springs_and_body(body_scene, point_scene):
    for scene in (point_scene, body_scene):
        xml = xval.mujoco_xml(scene, 2e-4)
        ET.fromstring(xml)  # well-formed
        m = mujoco.MjModel.from_xml_string(xml)
        N, mu, EA = scene.string.elements, scene.string.mass_per_length, scene.string.axial_stiffness
        l = scene.initial.deployed_length / N
        assert m.ntendon == N and m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4 and m.opt.timestep == 2e-4
        np.testing.assert_allclose(m.tendon_stiffness, EA / l, rtol=1e-15)
        np.testing.assert_allclose(m.tendon_lengthspring[:, 0], l, rtol=1e-15)
        np.testing.assert_allclose(m.tendon_lengthspring[:, 1], l, rtol=1e-15)
        assert np.all(m.tendon_damping == 0) and np.all(m.dof_damping == 0) and np.all(m.dof_armature == 0)
        np.testing.assert_allclose(m.opt.gravity, [0, 0, scene.g])
        # total mass = string + end mass (lumped: interior nodes μl, the last μl/2 + m_b)
        assert m.body_mass.sum() == pytest.approx(mu * l * (N - 0.5) + scene.body.mass, rel=1e-14)
    # the free body: inertia about its frame origin (the attachment point) = J_o (the node's
    # lumped mass sits at that origin and adds nothing there)
    model = build_model(body_scene)
    M, com, J = xval_mujoco._combined_inertia(model.m_b, model.J_c, model.rho_c, 0.0625)
    J_origin = J + M * (com @ com * np.eye(3) - np.outer(com, com))
    np.testing.assert_allclose(J_origin, model.J_o, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(M * com, model.m_b * model.rho_c, rtol=1e-14)


def test_moordyn_state_file_roundtrip(tmp_path):
    head = b"MoorDyn\x02\x07" + (0).to_bytes(8, "little") + (2).to_bytes(8, "little")
    blocks = [np.arange(6.0).reshape(1, 6), np.arange(24.0).reshape(4, 6) / 7]
    xval_moordyn._write_state(tmp_path / "s.bin", head, blocks)
    h2, b2 = xval_moordyn._read_state(tmp_path / "s.bin")
    assert h2 == head and all(np.array_equal(a, b) for a, b in zip(blocks, b2))
    (tmp_path / "bad.bin").write_bytes(b"NotMoorDyn")
    with pytest.raises(RuntimeError, match="not a MoorDyn state file"):
        xval_moordyn._read_state(tmp_path / "bad.bin")


# ------------------------------------------------------------------------------------------
# Refusals
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scene, named", [
    (lambda: load_scene("deployment"), "a reel"),
    (lambda: load_scene("fixed_length", effects=["elasticity", "gravity", "rigid_body", "slack"]), "effect 'slack'"),
    (lambda: load_scene("fixed_length", effects=["elasticity", "gravity", "axial_damping"], axial_damping=0.1,
                        angular_velocity=[0, 0, 0]), "effect 'axial_damping'"),
    (lambda: load_scene("near_slack"), "initial.stretch = 0.95"),
])
def test_untranslatable_scenes_are_refused_naming_why(scene, named):
    with pytest.raises(xval.Untranslatable, match=named):
        xval.check_scene(scene())


def test_moordyn_is_not_given_a_rigid_body(body_scene):
    with pytest.raises(xval.Untranslatable, match="moordyn cannot translate.*'rigid_body'"):
        xval.moordyn_input(body_scene, 1e-4)
    xval.check_scene(body_scene)  # the study runs the body against MuJoCo only: accepted


def test_cli_refuses_with_exit_code_2(capsys, tmp_path):
    assert cli_main(["xval", "--scenes", "deployment", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "cannot translate scene 'deployment'" in err and "a reel" in err
    assert not (tmp_path / "x").exists()  # refused before any work
    assert cli_main(["xval", "--elements", "5", "--out", str(tmp_path / "x")]) == 2
    assert "--elements" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# Tables and README from known synthetic runs (no simulation)
# ------------------------------------------------------------------------------------------
def test_tables_and_readme_from_synthetic_runs(tmp_path, body_scene):
    """Tips x_N(t) = X(t) + c_code/N²: observed order 2, Richardson limits equal X, the lumped
    codes' error ratio c_lumped/c_consistent, and the README quotes those numbers."""
    times = np.linspace(0.0, 1.0, 21)
    X = np.stack([np.sin(times), np.cos(times), times], axis=1)
    coef = {"ours_consistent": 1.0, "ours_lumped": -2.0, "moordyn": -2.0, "mujoco": -2.0}
    # the same discrete model: the reference and the outside codes (at dt and dt/2) off the lumped
    # LGVI by known small distances (metres along e1); at N = 5, MoorDyn in water 2e-10 m and MuJoCo
    # with the rigid body 3e-9 m more (over the tolerance: the README must say so)
    off = {xval.REFERENCE_CODE: 0.0, "moordyn": 3e-12, "moordyn_half_dt": 1e-12, "mujoco": -4e-12, "mujoco_half_dt": 0.0}
    runs = {}
    for case, codes in xval.CASES.items():
        for N in (5, 10, 20, 40):
            r = {}
            for code in ("ours_consistent", "ours_lumped", xval.REFERENCE_CODE) + codes + tuple(c + "_half_dt" for c in codes):
                shape = np.array([1.0, 0.5, 0.25]) * coef[code.removesuffix("_half_dt").replace("_dop853", "")] / N**2
                shape[0] += off.get(code, 0.0) + {("in_water", 5, "moordyn"): 2e-10,
                                                  ("rigid_body", 5, "mujoco"): 3e-9}.get((case, N, code), 0.0)
                ref = code == xval.REFERENCE_CODE
                r[code] = xval.CodeRun(code, N, None if ref else 1e-4 / (2 if code.endswith("_half_dt") else 1),
                                       X + shape[None, :], 1000, 0.01 * N,
                                       {"min_strain": 1e-3, **({"rhs_evals": 12000} if ref else {})}
                                       if code.startswith("ours") else {})
            runs[(case, N)] = r
    study = xval.Runs(times, runs)
    readme = xval_report.write_outputs(study, body_scene, tmp_path, Provenance("python -m benchmark xval --test"))
    import pandas as pd

    lim = pd.read_csv(tmp_path / "limits.csv")
    assert lim.max_limit_distance_m.max() < 1e-11  # the outside codes sit 3e-12 and -4e-12 m off (`off`)
    conv = pd.read_csv(tmp_path / "self_convergence.csv").dropna()
    np.testing.assert_allclose(conv.observed_order, 2.0, atol=1e-9)
    err = pd.read_csv(tmp_path / "error_vs_limit.csv")
    np.testing.assert_allclose(err.lumped_over_consistent, 2.0, rtol=1e-9)
    cost = pd.read_csv(tmp_path / "cost.csv")
    steps = cost[cost.code != xval.REFERENCE_CODE]
    np.testing.assert_allclose(steps.us_per_step, 10.0 * steps.N, rtol=1e-12)  # 0.01 N s / 1000 steps
    refs = cost[cost.code == xval.REFERENCE_CODE]
    np.testing.assert_allclose(refs.us_per_rhs, 10.0 * refs.N / 12, rtol=1e-12)  # 0.01 N s / 12000 right-hand sides
    diff = pd.read_csv(tmp_path / "differences.csv")
    same = diff[(diff.case == "in_water") & (diff.pair == f"{xval.REFERENCE_CODE} - moordyn")]
    np.testing.assert_allclose(same.max_tip_distance_m, [2.03e-10, 3e-12, 3e-12, 3e-12], rtol=1e-3)
    assert set(same.measures) == {"same discrete model"} and all("DOP853" in c and "RK4 at 0.0001 s" in c for c in same.compared)
    text = readme.read_text()
    assert "at equal N: at most 2.03e-10 m over N = 5…40" in text  # in water
    assert "at equal N: at most 4.00e-12 m over N = 5…40" in text  # point mass: MuJoCo's 4e-12
    assert text.count("- Both are at most 1e-09 m at every N of this case.") == 2
    assert ("- NOT shown at every N: model difference above 1e-09 m for mujoco at N = 5: 3.00e-09 m; time error of the "
            "outside code above 1e-09 m for mujoco at N = 5: 3.00e-09 m.") in text  # rigid body
    assert "| 5 | 0.0001 | 2.03e-10 | 2.02e-10 | 0.00e+00 |" in text  # in water: vs DOP853, dt vs dt/2, LGVI
    assert "python -m benchmark xval --test" in text and "moordyn 2." in text and "mujoco " in text
    assert "lumped / consistent at equal N: 2.00 (N = 5), 2.00 (N = 10)" in text
    assert "| 40 | 0.0001 | 400.0 | 400.0 | 400.0 | 400.0 |" in text
    assert (tmp_path / "inputs" / "moordyn_point_mass_N5.txt").exists()
    assert (tmp_path / "inputs" / "mujoco_rigid_body_N40.xml").exists()
    assert (tmp_path / "convergence_rigid_body.png").stat().st_size > 10_000
    tips = np.load(tmp_path / "tips.npz")
    np.testing.assert_array_equal(tips["point_mass_N10_moordyn"], runs[("point_mass", 10)]["moordyn"].tip)
