"""Where a registered integrator or effect comes from: the project itself or a plugin package.

The project's own methods and effects are those the reelbench distribution registers (its
decorators and its own entry points); everything else is a guest: `benchmark run` sweeps it
only when asked, `list` marks it, and its rows in runs.csv carry its package and version.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import sys
from importlib import metadata
from typing import NamedTuple

#: The distribution of this repository; it ships one top-level package, reelbench
#: (reelbench.models, reelbench.integrators, reelbench.benchmark).
PROJECT = "reelbench"
PROJECT_PACKAGES = frozenset({PROJECT})


class Origin(NamedTuple):
    """A method's or effect's package and version; ``own``: shipped by the project itself."""

    package: str
    version: str
    own: bool

    def label(self) -> str:
        """"plugin, package my-stepper 0.1" (what `list` prints beside a guest)."""
        if self.own:
            return f"{self.package} {self.version}".strip()
        return f"plugin, package {self.package}" + (f" {self.version}" if self.version else " (version unknown)")


def _normal(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


@functools.lru_cache(maxsize=1)
def project_origin() -> Origin:
    try:
        version = metadata.version(PROJECT)
    except metadata.PackageNotFoundError:  # a checkout run from its root without being installed
        version = ""
    return Origin(PROJECT, version, True)


def of_distribution(dist) -> Origin | None:
    """The origin of an entry point's distribution (None when the entry point has none)."""
    if dist is None:
        return None
    name = dist.metadata["Name"] or getattr(dist, "name", "") or ""
    if _normal(name) == PROJECT:
        return project_origin()
    return Origin(name, dist.version or "", False)


def of_object(obj) -> Origin:
    """The origin of a class (or instance) registered by code: the project for its own
    packages, else the installed distribution holding its top-level module, else the module
    itself with no version (a script or a test registering a method at run time)."""
    cls = obj if isinstance(obj, type) else type(obj)
    top = (cls.__module__ or "").split(".")[0]
    if top in PROJECT_PACKAGES:
        return project_origin()
    dists = metadata.packages_distributions().get(top) or []
    for name in dists:
        try:
            return Origin(name, metadata.version(name), False)
        except metadata.PackageNotFoundError:
            continue
    return Origin(top or "?", "", False)


def source_digest(obj) -> str:
    """A hash (12 hex digits) of the source file that defines ``obj``'s class: a plugin's rows
    are recomputed on resume when its code changes, like the project's (`benchmark.core.store.code_version`)."""
    cls = obj if isinstance(obj, type) else type(obj)
    h = hashlib.sha256(f"{cls.__module__}.{cls.__qualname__}".encode())
    try:
        path = inspect.getsourcefile(cls) or inspect.getfile(sys.modules[cls.__module__])
        with open(path, "rb") as f:
            h.update(f.read())
    except (TypeError, OSError, KeyError):  # defined in a string or an interactive session: its name only
        pass
    return h.hexdigest()[:12]
