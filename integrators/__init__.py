"""Integrators behind one small interface (`Integrator.solve -> Trajectory`).

    from integrators import get_integrator
    traj = get_integrator("dop853").solve(scene, t_end=1.0, rtol=1e-10, atol=1e-12)

Built-in: ``lgvi`` and the symmetric ``lgvi_sym``, ``lgvi_yoshida4``, ``lgvi_suzuki4`` (registered by decorator). Baselines ``rk45``, ``radau``, ``dop853``,
``tsit5``, ``kvaerno5`` are registered through the ``reelbench.integrators`` entry-point
group, exactly as an outside plugin would be.
"""

from models import _jax  # noqa: F401  (float64 first)
from integrators.base import Capability, Integrator, Status, Trajectory, save_times
from integrators.lifecycle import FixedStepMethod, Guards, ODEProblem
from integrators.registry import ENTRY_POINT_GROUP, available, get_integrator, plugin_errors, register, unregister

__all__ = [
    "Capability",
    "ENTRY_POINT_GROUP",
    "FixedStepMethod",
    "Guards",
    "Integrator",
    "ODEProblem",
    "Status",
    "Trajectory",
    "available",
    "get_integrator",
    "plugin_errors",
    "register",
    "save_times",
    "unregister",
]
from integrators import lgvi  # noqa: F401,E402  (registers "lgvi")
from integrators import lgvi_sym  # noqa: F401,E402  (registers "lgvi_sym", "lgvi_yoshida4", "lgvi_suzuki4")
