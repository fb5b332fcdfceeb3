"""Names from JAX-backed modules, imported on first use.

The registry loads every method's module to list its name and capabilities, and the command
line imports the studies' modules to check their names; a module that imported JAX at the
top would make every refusal wait a second or more for it. Such a module binds ``jax``,
``jnp`` and the model's functions through these stand-ins instead: each imports its module
(``models._jax`` first, for float64) when it is first used.
"""

from __future__ import annotations

import importlib


class LazyModule:
    """Stands for ``module`` (or its attribute ``attr``): attribute access imports it."""

    def __init__(self, module: str, attr: str | None = None):
        self._module, self._attr = module, attr

    def _target(self):
        mod = importlib.import_module(self._module)
        return getattr(mod, self._attr) if self._attr else mod

    def __getattr__(self, name: str):
        return getattr(self._target(), name)


def lazy_function(module: str, name: str):
    """A function that imports ``module`` and calls its ``name`` (same arguments, same result)."""

    def call(*args, **kwargs):
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"{module}.{name}, imported on first call."
    return call


#: ``jax`` and ``jax.numpy`` as `models._jax` configures them (float64).
jax = LazyModule("reelbench.models._jax", "jax")
jnp = LazyModule("reelbench.models._jax", "jnp")
