"""Registry of integrators by name: built-ins by decorator, plugins by entry point.

A plugin package declares, in its own pyproject.toml::

    [project.entry-points."reelbench.integrators"]
    my_method = "my_package.module:MyIntegrator"

where ``MyIntegrator`` subclasses `integrators.Integrator`. The baselines of this project are
registered exactly that way (see this repository's pyproject.toml). Loading an entry point
imports its module only: the classes are JAX-free until they run.
"""

from __future__ import annotations

import difflib
from importlib.metadata import entry_points

from reelbench.integrators.base import Integrator
from reelbench.models import origin as _origin

ENTRY_POINT_GROUP = "reelbench.integrators"

_REGISTRY: dict[str, type[Integrator]] = {}
_PLUGIN_ERRORS: dict[str, str] = {}
#: the distribution of each method loaded through an entry point (the others: by their module)
_ORIGINS: dict[str, _origin.Origin] = {}


def register(cls: type[Integrator]) -> type[Integrator]:
    """Class decorator: register an `Integrator` subclass under ``cls.name``."""
    if not (isinstance(cls, type) and issubclass(cls, Integrator)):
        raise TypeError(f"{cls!r} is not an Integrator subclass")
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    existing = _REGISTRY.get(cls.name)
    if existing is not None and existing is not cls:
        raise ValueError(f"integrator name {cls.name!r} is taken by {existing.__module__}.{existing.__qualname__}")
    _REGISTRY[cls.name] = cls
    return cls


def unregister(name: str) -> None:
    """Forget the integrator (or failed plugin) registered as ``name``; unknown names are ignored.

    For tests and interactive sessions that register temporary methods: a later
    `available()` reloads an entry-point plugin of that name, if one is installed.
    """
    _REGISTRY.pop(name, None)
    _PLUGIN_ERRORS.pop(name, None)
    _ORIGINS.pop(name, None)


def _load_plugins() -> None:
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in _REGISTRY or ep.name in _PLUGIN_ERRORS:
            continue
        try:
            cls = ep.load()
            if getattr(cls, "name", None) != ep.name:
                raise ValueError(f"entry point {ep.name!r} loads a class named {getattr(cls, 'name', None)!r}")
            register(cls)
            found = _origin.of_distribution(getattr(ep, "dist", None))
            if found is not None:
                _ORIGINS[ep.name] = found
        except Exception as exc:  # a broken plugin must not take the others down
            _PLUGIN_ERRORS[ep.name] = f"{type(exc).__name__}: {exc}"


def available() -> list[str]:
    """Names of all registered integrators (built-ins and plugins)."""
    _load_plugins()
    return sorted(_REGISTRY)


def origin(name: str) -> _origin.Origin:
    """Where the registered method ``name`` comes from (`models.origin.Origin`): the project
    (its decorators and its own entry points) or a plugin's package and version."""
    _load_plugins()
    if name in _ORIGINS:
        return _ORIGINS[name]
    if name not in _REGISTRY:
        raise ValueError(f"unknown integrator {name!r}; available: {', '.join(sorted(_REGISTRY))}")
    return _origin.of_object(_REGISTRY[name])


def own() -> list[str]:
    """The project's own methods (those the reelbench distribution registers), sorted."""
    return [n for n in available() if origin(n).own]


def plugin_errors() -> dict[str, str]:
    """Entry points that failed to load, with the reason."""
    _load_plugins()
    return dict(_PLUGIN_ERRORS)


def get_integrator(name: str) -> Integrator:
    """An instance of the integrator registered as ``name``. (No method takes constructor
    options: a run's options go to ``solve``.)"""
    if not isinstance(name, str):
        raise ValueError(f"integrator name = {name!r} is invalid (allowed: a string, one of: "
                         f"{', '.join(available())})")
    if name not in _REGISTRY:  # scanning the installed distributions costs ~50 ms: only for a name not yet seen
        _load_plugins()
    if name not in _REGISTRY:
        if name in _PLUGIN_ERRORS:
            raise ValueError(f"integrator {name!r} failed to load: {_PLUGIN_ERRORS[name]}")
        close = difflib.get_close_matches(name, list(_REGISTRY), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown integrator {name!r}{hint}; available: {', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[name]()
