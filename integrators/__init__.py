"""Integrators behind one small interface (`Integrator.solve -> Trajectory`).

    from reelbench.integrators import get_integrator
    traj = get_integrator("dop853").solve(scene, t_end=1.0, rtol=1e-10, atol=1e-12)

Built-in: ``lgvi`` and the symmetric ``lgvi_sym``, ``lgvi_yoshida4``, ``lgvi_suzuki4``
(registered by decorator). Baselines ``rk45``, ``rk45_projected``, ``radau``, ``dop853``,
``tsit5``, ``dopri5``, ``dopri8``, ``kvaerno5`` are registered through the
``reelbench.integrators`` entry-point group, exactly as an outside plugin would be.

Importing this package, listing and describing the methods does not import JAX: the classes
import it inside the functions that trace and compile (through `models._jax`, which switches
JAX to float64 first).
"""

from reelbench.integrators.base import IMPLEMENTATIONS, Capability, Integrator, Status, Trajectory, save_times
from reelbench.integrators.fixed_step import FixedStepMethod, StepCode, StepResult
from reelbench.integrators.lifecycle import Guards, LibraryAdapter, ODEProblem, Outcome, Run
from reelbench.integrators.registry import ENTRY_POINT_GROUP, available, get_integrator, origin, plugin_errors, register, unregister

__all__ = [
    "Capability",
    "ENTRY_POINT_GROUP",
    "FixedStepMethod",
    "Guards",
    "IMPLEMENTATIONS",
    "Integrator",
    "LibraryAdapter",
    "ODEProblem",
    "Outcome",
    "Run",
    "Status",
    "StepCode",
    "StepResult",
    "Trajectory",
    "available",
    "get_integrator",
    "origin",
    "plugin_errors",
    "register",
    "save_times",
    "unregister",
]
from reelbench.integrators import lgvi  # noqa: F401,E402  (registers "lgvi")
from reelbench.integrators import lgvi_sym  # noqa: F401,E402  (registers "lgvi_sym", "lgvi_yoshida4", "lgvi_suzuki4")
