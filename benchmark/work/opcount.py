"""Count the floating-point operations plain numeric Python performs, by running it on counting
scalars.

`benchmark.work.work_rule` uses this to count the compiled floors' *own* arithmetic: their numba
kernels are plain Python loops over scalars, so running their source (numba's decorators made
no-ops) on `Counted` values counts every add, multiply, division and square root exactly as
written and executed — the same operations the compiled kernel performs (fastmath off: no
contraction, no reassociation), each counted once per execution, including the multiplications
by a tableau's zeros that the kernel does execute. Only ``float`` arithmetic on `Counted` values
is counted: index arithmetic on ints and the loops' control are not flops.

    with OpCounter(modules) as ops:
        f(counted_array(x), Counted(h))
    ops.flops, ops.counts["div"]
"""

from __future__ import annotations

import collections
import importlib
import math
import sys
import types
from pathlib import Path

import numpy as np

#: The kinds of operation counted; "cmp" (comparisons) is counted but is not a flop.
FLOP_KINDS = ("add", "mul", "div", "sqrt", "neg", "abs")

_active: list[collections.Counter] = []


def _tally(kind: str) -> None:
    for counter in _active:
        counter[kind] += 1


def _value(x) -> float:
    return x.v if isinstance(x, Counted) else float(x)


class Counted:
    """A float whose arithmetic is tallied by every open `OpCounter`."""

    __slots__ = ("v",)

    def __init__(self, v):
        self.v = float(v)

    def _binary(self, other, kind, fn):
        _tally(kind)
        return Counted(fn(self.v, _value(other)))

    def __add__(self, o): return self._binary(o, "add", lambda a, b: a + b)
    def __radd__(self, o): return self._binary(o, "add", lambda a, b: b + a)
    def __sub__(self, o): return self._binary(o, "add", lambda a, b: a - b)
    def __rsub__(self, o): return self._binary(o, "add", lambda a, b: b - a)
    def __mul__(self, o): return self._binary(o, "mul", lambda a, b: a * b)
    def __rmul__(self, o): return self._binary(o, "mul", lambda a, b: b * a)
    def __truediv__(self, o): return self._binary(o, "div", lambda a, b: a / b)
    def __rtruediv__(self, o): return self._binary(o, "div", lambda a, b: b / a)

    def __neg__(self):
        _tally("neg")
        return Counted(-self.v)

    def __pos__(self):
        return self

    def __abs__(self):
        _tally("abs")
        return Counted(abs(self.v))

    def _compare(self, other, fn):
        _tally("cmp")
        return fn(self.v, _value(other))

    def __lt__(self, o): return self._compare(o, lambda a, b: a < b)
    def __le__(self, o): return self._compare(o, lambda a, b: a <= b)
    def __gt__(self, o): return self._compare(o, lambda a, b: a > b)
    def __ge__(self, o): return self._compare(o, lambda a, b: a >= b)
    def __eq__(self, o): return self._compare(o, lambda a, b: a == b)
    def __ne__(self, o): return self._compare(o, lambda a, b: a != b)
    __hash__ = None

    def __float__(self):
        return self.v

    def sqrt(self):  # what numpy's ufunc calls on an object element
        _tally("sqrt")
        return Counted(math.sqrt(self.v))

    def __repr__(self):
        return f"Counted({self.v!r})"


class OpCounter:
    """Tallies the operations on `Counted` values while it is open (``with``); the ``modules``
    (from `load_plain`) meanwhile allocate `Counted` arrays and tally their square roots."""

    def __init__(self, modules=()):
        self.counts: collections.Counter = collections.Counter()
        self._modules = tuple(modules)

    def __enter__(self):
        _active.append(self.counts)
        for m in self._modules:
            m.np, m.math = _NUMPY, _MATH
        return self

    def __exit__(self, *exc):
        _active.remove(self.counts)
        for m in self._modules:
            m.np, m.math = np, math
        return False

    @property
    def flops(self) -> int:
        """Every counted operation but comparisons (a division and a square root count one each)."""
        return sum(self.counts[k] for k in FLOP_KINDS)


def counted_array(a) -> np.ndarray:
    """An object array of `Counted` with ``a``'s shape and values (a float array, list or scalar)."""
    a = np.asarray(a, dtype=float)
    out = np.empty(a.shape, dtype=object)
    for idx in np.ndindex(a.shape):
        out[idx] = Counted(a[idx])
    return out


def counted(value):
    """``value`` with every float (array) in it made `Counted` (tuples recursively; ints kept)."""
    if isinstance(value, tuple):
        return type(value)(*map(counted, value)) if hasattr(value, "_fields") else tuple(map(counted, value))
    if isinstance(value, np.ndarray) and value.dtype.kind == "f":
        return counted_array(value)
    if isinstance(value, (float, np.floating)):
        return Counted(value)
    return value


def _counted_zeros(shape, *args, **kwargs):
    return counted_array(np.zeros(shape))


#: What a kernel's ``np`` and ``math`` become: numpy with fresh arrays of `Counted`, and square
#: roots tallied (``math.sqrt`` would convert to a plain float and escape the count).
class _Overlay:
    """A module's namespace with some names replaced; every other name looked up in the module."""

    def __init__(self, module, **replaced):
        self.__dict__.update(replaced)
        self._module = module

    def __getattr__(self, name):
        return getattr(self._module, name)


def _sqrt(x):
    return x.sqrt() if isinstance(x, Counted) else np.sqrt(x)


_NUMPY = _Overlay(np, zeros=_counted_zeros, empty=_counted_zeros, sqrt=_sqrt)
_MATH = _Overlay(math, sqrt=_sqrt, isfinite=lambda x: math.isfinite(_value(x)))


def load_plain(directory: Path, names: tuple[str, ...]) -> dict[str, types.ModuleType]:
    """Import the modules ``names`` from ``directory`` as plain Python: numba's ``njit`` a no-op,
    ``prange`` = ``range`` (an `OpCounter` given them makes their ``np`` and ``math`` count while
    it is open). They import each other by name, so they are loaded together; ``sys.modules`` is
    left as it was."""
    fake_numba = types.ModuleType("numba")
    fake_numba.njit = lambda *a, **k: a[0] if a and callable(a[0]) else (lambda f: f)
    fake_numba.prange = range
    saved = {k: sys.modules.get(k) for k in ("numba", *names)}
    sys.modules["numba"] = fake_numba
    sys.path.insert(0, str(directory))
    modules = {}
    try:
        for name in names:
            sys.modules.pop(name, None)
            modules[name] = importlib.import_module(name)
    finally:
        sys.path.remove(str(directory))
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    return modules
