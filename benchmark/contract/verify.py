"""The plugin contract, checked: ``python -m benchmark verify NAME`` and its importable twins.

In the spirit of scikit-learn's ``check_estimator``: a plugin author (or this project's own
test suite) runs one function on an integrator or an effect and gets one `Check` per rule of
the contract (integrators/README.md, "The plugin contract"; models/README.md, "Adding an
effect"), each with the figure it was judged by::

    from reelbench.benchmark.contract.verify import check_integrator, check_effect
    check_integrator("my_method")          # raises ContractError naming every failed check
    check_effect("tip_spring", scene="my_scene.toml")

An integrator is checked by `check_integrator` (`benchmark.contract.integrator`), an effect by
`check_effect` (`benchmark.contract.effect`): each module's docstring lists its checks, and
`benchmark.contract.checks` holds what they share. This module is the command: `kind_of` and
`verify`.

Small N and short horizons: a method takes seconds to tens of seconds (its compilations).
"""

from __future__ import annotations

from typing import Callable

from reelbench.benchmark.contract.checks import Check, ContractError, small_scene  # noqa: F401 - the contract's names
from reelbench.benchmark.contract.effect import check_effect, effect_scene  # noqa: F401
from reelbench.benchmark.contract.integrator import check_integrator  # noqa: F401


def kind_of(name: str) -> str:
    """"integrator" or "effect" for a registered name; ValueError naming both registries otherwise."""
    from reelbench.integrators import available
    from reelbench.models.effects import EFFECTS, ensure_known

    if name in available():
        return "integrator"
    ensure_known([name])
    if name in EFFECTS:
        return "effect"
    raise ValueError(f"verify: {name!r} is neither a registered integrator ({', '.join(available())}) nor an effect "
                     f"({', '.join(EFFECTS)}); install the plugin first (see `python -m benchmark list`)")


def verify(name: str, *, scene=None, overrides: dict | None = None, log: Callable[[str], None] = print) -> int:
    """``python -m benchmark verify NAME``: one line per check, then a summary; exit status 0
    when every check holds, 1 otherwise."""
    import time

    t0 = time.perf_counter()
    kind = kind_of(name)
    log(f"verify {kind} {name!r}:")
    if kind == "integrator":
        checks = check_integrator(name, log=log, raise_on_failure=False)
    else:
        checks = check_effect(name, scene=scene, overrides=overrides, log=log, raise_on_failure=False)
    failed = [c.name for c in checks if not c.ok]
    log(f"{len(checks) - len(failed)} of {len(checks)} checks hold ({time.perf_counter() - t0:.0f} s)"
        + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0
