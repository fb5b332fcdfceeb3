"""JAX runs in float64 everywhere in reelbench; this is the one place that says so, and the one
place that sets XLA options (they must be in ``XLA_FLAGS`` before JAX initialises its backend).

XLA on CPU runs the body of a small ``lax.while_loop`` / ``scan`` one operation at a time, so
a step of ~175 tiny operations (the LGVI at N = 10) costs their launch overhead, not their
arithmetic. ``xla_cpu_small_while_loop_byte_threshold`` raises the size below which XLA
compiles such a loop as one fused native loop instead: measured on this project's loops
(`python -m benchmark speed`, one core) the LGVI runs 4-5x faster per step and diffrax's
Tsit5 1.5-3x faster, with compile times unchanged or shorter. The option is appended to a
user's own ``XLA_FLAGS`` (never replacing them) unless the user already set it;
``REELBENCH_XLA_DEFAULTS=0`` turns it off (for A/B measurements). `xla_flags()` is what the
results record as provenance.
"""

import os

#: XLA options reelbench adds to XLA_FLAGS (see the module docstring for why).
DEFAULT_XLA_FLAGS = ("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000000",)


def append_xla_flags(flags, env=os.environ) -> str:
    """Append ``flags`` to ``env["XLA_FLAGS"]``, skipping any whose option name is already set
    there (a user's own value wins). Returns the new value."""
    current = env.get("XLA_FLAGS", "").split()
    names = {f.split("=", 1)[0] for f in current}
    added = [f for f in flags if f.split("=", 1)[0] not in names]
    value = " ".join(current + added)
    if value:
        env["XLA_FLAGS"] = value
    return value


if os.environ.get("REELBENCH_XLA_DEFAULTS", "1") != "0":
    append_xla_flags(DEFAULT_XLA_FLAGS)

import jax  # noqa: E402  (after XLA_FLAGS, on purpose)

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402  (after the flag, on purpose)

#: XLA_FLAGS as JAX's backend will read them (fixed once the backend initialises).
_XLA_FLAGS_AT_IMPORT = os.environ.get("XLA_FLAGS", "")


def xla_flags() -> str:
    """The XLA_FLAGS this process's JAX runs with (for the results' provenance)."""
    return _XLA_FLAGS_AT_IMPORT


__all__ = ["jax", "jnp", "xla_flags", "append_xla_flags", "DEFAULT_XLA_FLAGS"]
