"""The right-hand side the ODE baselines (scipy, diffrax) integrate, and its Jacobian.

Two implementations of the same equations (models/README.md) on the quaternion ODE state:

* ``"closed_form"`` (default): `models.closed_form.ClosedFormEOM.ode_rhs`, hand-derived, with
  an O(N) structured solve of M ẇ = F. It agrees with the autodiff path to ~1e-15
  (tests/test_rhs.py) and costs O(N) per call instead of O(N³).
* ``"autodiff"``: `StringPendulum.ode_rhs`, the Lagrangian differentiated by JAX (mass matrix
  by ``jacfwd`` of ``grad``, dense solve). Kept as the independent check and selectable with
  ``solve(..., rhs="autodiff")``.

Jacobian (Radau; Kvaerno5's Newton differentiates the term itself, the same way): forward-mode
autodiff (``jacfwd``) of the chosen right-hand side, jitted, one call per Jacobian. Measured
against scipy's finite differences with a ``jac_sparsity`` pattern, this wins by far: through
the Schur complement on (s̈, q̈_{N+1}, Ω̇) every acceleration depends on every coordinate
(M⁻¹ is dense), so the pattern is dense in the velocity rows and finite differences need ny
right-hand sides per Jacobian, while ``jacfwd`` pushes all ny tangents through one
vectorised evaluation. Measured (one core, per Jacobian, called from numpy): fixed_length
N = 10 (ny = 67): jacfwd of the closed form 60 µs, of the autodiff RHS 124 µs, finite
differences 2.4 ms dense / 3.4 ms with the sparsity pattern (scipy's column grouping finds
few independent columns: 1374 of 4489 entries are structurally nonzero, in dense rows);
deployment N = 40 (ny = 250): 0.65 ms, 52 ms, 11 ms, 23 ms.
"""

from __future__ import annotations

import functools

#: The selectable right-hand sides; the first is the default.
RHS_CHOICES = ("closed_form", "autodiff")
DEFAULT_RHS = RHS_CHOICES[0]


def check_rhs(rhs) -> str:
    """``rhs`` if it names a known right-hand side, else ValueError naming the allowed values."""
    if not isinstance(rhs, str) or rhs not in RHS_CHOICES:
        raise ValueError(f"rhs = {rhs!r} is invalid (allowed: {', '.join(map(repr, RHS_CHOICES))})")
    return rhs


def closed_form_of(model):
    """The closed-form equations of a model (cached per model, like `models.build_model`; a
    model bound to run-time values (`StringPendulum.bind`) gets new ones each time: they hold
    values of the trace that asked, which no other trace may see)."""
    from reelbench.models.closed_form import ClosedFormEOM

    if model.is_bound:
        made = model.__dict__.get("_closed_form")
        return made if made is not None else ClosedFormEOM(model)
    return _closed_form_cached(model)


def prepare(model):
    """Build a bound model's closed form once, where it was bound (the top of a compiled
    program, outside its loops), so that every step reuses the quantities it derives from the
    values instead of deriving them again inside the loop. Only there: what it holds belongs to
    that trace."""
    from reelbench.models.closed_form import ClosedFormEOM

    if model.is_bound and "_closed_form" not in model.__dict__:
        model.__dict__["_closed_form"] = ClosedFormEOM(model)
    return model


@functools.lru_cache(maxsize=64)
def _closed_form_cached(model):
    from reelbench.models.closed_form import ClosedFormEOM

    return ClosedFormEOM(model)


def ode_rhs(model, rhs: str = DEFAULT_RHS):
    """The traceable function f(t, y) of the chosen right-hand side."""
    return closed_form_of(model).ode_rhs if check_rhs(rhs) == "closed_form" else model.ode_rhs


def device_values(model):
    """The model's numbers on the device, packed in one vector (`StringPendulum.value_vector`),
    once per model: the run-time argument of every compiled program of its structure."""
    cached = model.__dict__.get("_device_values")
    if cached is None:
        from reelbench.models._jax import jax

        cached = model.__dict__["_device_values"] = jax.device_put(model.value_vector())
    return cached


@functools.lru_cache(maxsize=128)
def _rhs_program(structure, template, rhs: str):
    """f(values, t, y), jitted once per model structure and rhs (``template``: the first model of
    that structure seen; any other binds its own values on the same structure)."""
    from reelbench.models._jax import jax

    return jax.jit(lambda values, t, y: ode_rhs(template.bind(values), rhs)(t, y))


@functools.lru_cache(maxsize=128)
def _jacobian_program(structure, template, rhs: str):
    from reelbench.models._jax import jax

    return jax.jit(lambda values, t, y: jax.jacfwd(ode_rhs(template.bind(values), rhs), argnums=1)(t, y))


def program(cache, model, *args):
    """``cache(structure, template, *args)`` for ``model``: the template is the first model of
    its structure asked for (the key holds the structure; the template only gives it)."""
    key = structure_of(model)
    template = _TEMPLATES.setdefault(key, model)
    return cache(key, template, *args)


#: the first model seen of each structure (`program`); a model is small, the set of structures too
_TEMPLATES: dict = {}


def structure_of(model):
    """The compile-cache key of a model: its structure where its programs are shared
    (`StringPendulum.structure_key`), else the model itself (as before values were arguments)."""
    return model.structure_key() if model.shares_programs else ("model", model)


def rhs_jit(model, rhs: str = DEFAULT_RHS):
    """Jitted f(t, y) of ``model``, called from the host (scipy's methods, the work count):
    the structure's program (`_rhs_program`) with this model's numbers as constants of a small
    program of its own. XLA folds them there: a call from numpy cost 12 % more with the numbers
    as arguments (73 vs 83 µs, retrieval N = 10, one pinned core), and scipy's solves are made
    of such calls; compiling one right-hand side takes a fraction of a second."""
    return _host_program(model, rhs, False)


def jacobian_jit(model, rhs: str = DEFAULT_RHS):
    """Jitted ∂f/∂y by forward-mode autodiff of the chosen right-hand side (see the module
    docstring for why forward mode); a program per model, like `rhs_jit`."""
    return _host_program(model, rhs, True)


@functools.lru_cache(maxsize=128)
def _host_program(model, rhs: str, jacobian: bool):
    import numpy as np

    from reelbench.models._jax import jax

    shared = program(_jacobian_program if jacobian else _rhs_program, model, rhs)
    values = np.asarray(model.value_vector())  # numpy: a constant of this program
    return jax.jit(lambda t, y: shared(values, t, y))
