"""JAX runs in float64 everywhere in reelbench; this is the one place that says so."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402  (after the flag, on purpose)

__all__ = ["jax", "jnp"]
