"""The plugin contract check (`python -m benchmark verify`, benchmark/contract/verify.py).

Default run: a representative subset -- a method that ignores the guards and an effect with a
wrong gradient and a wrong power are caught (so the checks can fail); the built-in `rk45`
(an adaptive library adapter) and `carnot` (a dissipative reel force) pass; and the example
plugins of integrators/README.md and models/README.md, installed into a temporary site
directory as a package would be, pass `python -m benchmark verify` as documented. Under
``-m slow``: every built-in integrator and effect.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from reelbench.benchmark.contract.verify import ContractError, check_effect, check_integrator
from reelbench.integrators import Capability, Integrator, Trajectory, registry
from reelbench.models import EFFECTS
from reelbench.models.effects import ENTRY_POINT_GROUP as EFFECT_GROUP
from reelbench.models.effects import Effect, PotentialTerm


ROOT = Path(__file__).resolve().parent.parent


def _failed(checks):
    return {c.name for c in checks if not c.ok}


class UnguardedEuler(Integrator):
    """Forward Euler in numpy that declares order 2 and ignores every budget and guard."""

    name = "verify_unguarded_euler"
    capabilities = frozenset({Capability.FIXED_STEP})
    order = 2
    description = "forward Euler without guards (test only)"

    def solve(self, scene, t_end=None, *, dt=None, save_every=None, **options):
        from reelbench.integrators.rhs import rhs_jit
        from reelbench.models import build_model

        if dt is None or dt <= 0:
            raise ValueError("dt is required")
        model = build_model(scene)
        lay, f = model.layout, rhs_jit(model)
        t_end = scene.t_end if t_end is None else t_end
        n, every = int(round(t_end / dt)), int(round((save_every or dt) / dt))
        y, ys = np.asarray(model.initial_ode_state()), []
        for k in range(n + 1):
            if k % every == 0:
                ys.append(y)
            y = y + dt * np.asarray(f(k * dt, y))
        ys = np.array(ys)
        return Trajectory(t=np.arange(len(ys)) * dt * every, x=ys[:, lay.y_x], attitude=ys[:, lay.y_quat],
                          attitude_kind="quaternion", velocity=ys[:, lay.y_w], work=np.zeros(len(ys)),
                          integrator=self.name, stats={"steps": n})


def test_a_method_that_ignores_the_contract_fails_and_says_where():
    checks = check_integrator(UnguardedEuler, raise_on_failure=False)
    failed = _failed(checks)
    by_name = {c.name: c for c in checks}
    print("\n".join(c.line() for c in checks))
    # order 1, not the declared 2; a step longer than the run taken; max_steps ignored; the string runs
    # out and it goes on; a blow-up returned as ok; no work count (measured: 9 of the 11 checks fail)
    assert {"order fixed_length", "order reel", "arguments", "budget", "length limit", "energy guard",
            "flops"} <= failed, failed
    observed = float(re.search(r"observed ([\d.]+)", by_name["order fixed_length"].figure).group(1))
    assert 0.9 < observed < 1.3, observed  # forward Euler (measured 1.12)
    assert "declarations" not in failed and "deterministic" not in failed
    assert registry._REGISTRY.get(UnguardedEuler.name) is None  # registered for the checks only


class WrongSpring(Effect):
    """A spring with a gradient twice too large and a damper claiming the wrong power."""

    name = "verify_wrong_spring"
    forcing = True
    dissipative = True

    def potentials(self, model):
        def V(x, R):
            return 0.5 * 3.0 * (model.nodes(x)[-1] @ model.nodes(x)[-1])

        def dV(x, R):
            from reelbench.models._jax import jnp

            return model.over_w(dq=jnp.zeros((model.N, 3)).at[-1].set(2 * 3.0 * model.nodes(x)[-1]))

        return {"V_wrong_spring": PotentialTerm(V, dV)}

    def string_forces(self, model):
        return {"Q_wrong_damper": lambda t, x, w: model.over_w(dq=-0.1 * w[model.layout.nodes])}

    def power(self, model, t, x, w):
        v = w[model.layout.nodes]
        return -0.2 * (v @ v)  # twice the force's Q·w


def test_an_effect_with_a_wrong_gradient_and_power_fails():
    checks = check_effect(WrongSpring(), raise_on_failure=False)
    print("\n".join(c.line() for c in checks))
    assert {"gradient V_wrong_spring", "power", "energy balance"} <= _failed(checks), _failed(checks)
    assert "verify_wrong_spring" not in EFFECTS  # registered for the checks only
    # the pytest twin raises, naming every failed check
    with pytest.raises(ContractError, match=r"effect 'verify_wrong_spring' fails \d+ of \d+ checks") as err:
        check_effect(WrongSpring())
    assert "FAIL  gradient V_wrong_spring" in str(err.value) and "ok " not in str(err.value)
    assert {c.name for c in err.value.checks if not c.ok} == _failed(checks)


@pytest.mark.parametrize("name", ["carnot"])
def test_a_builtin_effect_passes(name):
    assert all(c.ok for c in check_effect(name))


def test_a_builtin_library_adapter_passes():
    checks = check_integrator("rk45")
    names = {c.name for c in checks}
    assert {"order fixed_length", "order reel", "energy guard", "capability adaptive", "flops"} <= names


#: Built-in methods verify flags, with what it measured (deterministic figures, not timings).
#: (Empty: radau's order-reduced 4 while reeling is now declared, `integrators.scipy_ivp.Radau.orders`.)
KNOWN: dict[str, str] = {}


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(strict=True, reason=KNOWN[n]))
                                  if n in KNOWN else n for n in sorted(registry.own())])
def test_every_builtin_integrator_passes(name):
    check_integrator(name, log=print)


#: Effects whose keys have no default are checked in a shipped scene that lists them, as
#: `verify --scenes` does (without one, check_effect refuses them: ValueError naming the keys).
EFFECT_SCENES = {"buoyancy": "towed", "drag": "towed"}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(EFFECTS))
def test_every_builtin_effect_passes(name):
    check_effect(name, scene=EFFECT_SCENES.get(name), log=print)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["buoyancy", "drag"])
def test_the_fluid_effects_pass_on_an_off_centre_body(name):
    """towed_offset: the body's drag at its offset centre of mass is a body load (its moment's
    power Ω·M is checked); its buoyancy there turns the body through ∂V/∂η."""
    checks = check_effect(name, scene="towed_offset", log=print)
    if name == "drag":
        assert "body loads' Ω·M" in next(c for c in checks if c.name == "power").figure


def test_an_effect_another_needs_is_removed_with_it_when_its_keys_are_checked():
    """buoyancy's keys given without it must be refused naming the key, in a scene where drag
    (which needs buoyancy) is listed too: the check removes drag and its keys as well."""
    from reelbench.benchmark.contract.effect import _scene_keys
    from reelbench.models import load_scene

    check = _scene_keys("buoyancy", load_scene("towed"))
    assert check.ok, check.figure
    assert check.figure.startswith("11 of 11"), check.figure


# ------------------------------------------------------------------------------------------
# The documented plugins, installed as packages, pass the command as documented
# ------------------------------------------------------------------------------------------
def _readme_block(path: Path, first_line: str, lang: str = "python") -> str:
    text = path.read_text(encoding="utf-8")
    return re.search(rf"```{lang}\n({re.escape(first_line)}.*?)```", text, flags=re.S).group(1)


def install_documented(readme: Path, module_first_line: str, site: Path) -> dict:
    """Install the README's example package into ``site`` as pip would: its module, and a
    dist-info with the name, version and entry points of the README's own pyproject.toml (a
    wheel cannot be built offline here; the metadata is what the registry reads). Returns the
    parsed pyproject."""
    import tomllib

    pyproject = tomllib.loads(_readme_block(readme, "[build-system]", lang="toml"))
    project = pyproject["project"]
    [module] = pyproject["tool"]["setuptools"]["py-modules"]
    site.mkdir(parents=True, exist_ok=True)
    (site / f"{module}.py").write_text(_readme_block(readme, f'"""{module}.py'))
    dist = site / f"{module}-{project['version']}.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n")
    (dist / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items())
        for group, entries in project["entry-points"].items()))
    return pyproject


def _benchmark(site: Path, *args, cwd: Path = ROOT):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(site)]))
    return subprocess.run([sys.executable, "-m", "benchmark", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def _check_lines(stdout: str) -> list[str]:
    return [ln for ln in stdout.splitlines() if ln.startswith(("ok ", "FAIL"))]


def test_the_documented_integrator_plugin_passes_verify(tmp_path):
    readme = ROOT / "integrators" / "README.md"
    pyproject = install_documented(readme, '"""my_stepper.py', tmp_path / "site")
    assert pyproject["project"]["entry-points"]["reelbench.integrators"] == {
        "symplectic_euler": "my_stepper:SymplecticEuler"}
    text = readme.read_text()
    assert "`pip install -e ./my-stepper`" in text and "`python -m benchmark verify symplectic_euler`" in text
    proc = _benchmark(tmp_path / "site", "verify", "symplectic_euler")
    print(proc.stdout)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    checks = _check_lines(proc.stdout)
    assert len(checks) >= 10 and all(ln.startswith("ok ") for ln in checks)
    assert any(ln.startswith("ok    order fixed_length: observed 1.0") for ln in checks)
    assert any("energy guard" in ln and "status diverged" in ln for ln in checks)  # the blow-up is reported
    assert re.search(r"^\d+ of \d+ checks hold", proc.stdout.splitlines()[-1])


def test_the_documented_effect_plugin_passes_verify(tmp_path):
    readme = ROOT / "models" / "README.md"
    site = tmp_path / "site"
    pyproject = install_documented(readme, '"""my_effects.py', site)
    assert set(pyproject["project"]["entry-points"][EFFECT_GROUP]) == {"tip_spring", "tip_damper", "spin_damper"}
    work = tmp_path / "work"
    work.mkdir()
    (work / "tip_spring_demo.toml").write_text(_readme_block(readme, 'name = "tip_spring_demo"', lang="toml"))
    text = " ".join(readme.read_text().split())
    assert "`python -m benchmark verify tip_spring tip_damper spin_damper --scenes tip_spring_demo.toml`" in text
    proc = _benchmark(site, "verify", "tip_spring", "tip_damper", "spin_damper", "--scenes", "tip_spring_demo.toml",
                      cwd=work)
    print(proc.stdout)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    reports = proc.stdout.split("verify effect ")[1:]
    assert [r.split(":")[0] for r in reports] == ["'tip_spring'", "'tip_damper'", "'spin_damper'"]
    for report, term in zip(reports, ("gradient V_tip_spring", "power", "power")):
        checks = _check_lines(report)
        assert checks and all(ln.startswith("ok ") for ln in checks)
        names = {ln.split(":")[0].split(maxsplit=1)[1] for ln in checks}
        assert {"declarations", "power", "energy balance", "scene keys", term} <= names, names
        keys = next(ln for ln in checks if ln.startswith("ok    scene keys"))
        assert re.search(r"(\d+) of \1 broken values refused", keys), keys
    assert "Q·w = claimed power" in reports[1] and "≤ 0 (dissipative)" in reports[1]
    # the spin damper's moment: its power Ω·M checked against body_power, and E − W kept
    assert "body loads' Ω·M" in reports[2] and "≤ 0 (dissipative)" in reports[2], reports[2]
    # without a scene, its required keys are named and the command refuses (exit 2) before any work
    bare = _benchmark(site, "verify", "tip_spring", cwd=work)
    assert bare.returncode == 2 and "tip_spring.stiffness" in bare.stderr and "--scenes" in bare.stderr, bare.stderr
    listing = _benchmark(site, "list", cwd=work)
    assert "tip_damper (plugin, package my-effects 0.1)" in listing.stdout, listing.stdout


def test_verify_refuses_unknown_names_and_misplaced_options():
    from reelbench.benchmark.cli.main import main

    assert main(["verify", "no_such_method"]) == 2
    assert main(["verify", "lgvi", "--scenes", "fixed_length"]) == 2
    assert main(["verify", "carnot", "--scenes", "fixed_length"]) == 2  # the scene does not list it


def test_a_method_that_still_declares_a_study_setting_fails_its_declarations_and_is_told_where_it_went():
    """`sweep_rtols`, `horizon_settings`, … moved from the integrator into the studies: a plugin that
    still declares one would be silently ignored, so the contract refuses it and names the study's table."""
    from reelbench.benchmark.contract import integrator as contract
    from reelbench.integrators import get_integrator

    lie_rk4 = type(get_integrator("lie_rk4"))
    assert contract._declarations(lie_rk4()).ok
    stale = type("StaleLieRK4", (lie_rk4,), {"sweep_rtols": (1e-4,), "horizon_settings": {"dt": 0.01}})()
    check = contract._declarations(stale)
    assert not check.ok
    assert "declares sweep_rtols" in check.figure and "benchmark.runs.sweep.SWEEP_RTOLS" in check.figure
    assert "declares horizon_settings" in check.figure and "benchmark.studies.horizon.SETTINGS" in check.figure
