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

Also set here, once, before JAX and equinox are imported:

* ``EQX_ON_ERROR=nan`` unless the user set it: equinox's runtime checks (``error_if``) then
  return NaN instead of raising through a host callback, so no compiled program carries one
  (reelbench checks its inputs before a solve instead) and every program can enter JAX's
  persistent cache. Set before equinox's first import (it reads the variable then).
* JAX's persistent compilation cache, on by default in the user's cache directory
  (``models.io.user_cache_dir()/jax``: ``$REELBENCH_CACHE``, ``$XDG_CACHE_HOME/reelbench`` or
  ``~/.cache/reelbench``): a second process loads
  the compiled programs instead of compiling them again. ``REELBENCH_COMPILE_CACHE=0`` turns it
  off, a path puts it there. Every program is cached, however fast it compiled.
* Synchronous dispatch on CPU (``jax_cpu_enable_async_dispatch=False``, where this JAX has the
  option): a small call from Python (scipy's right-hand side) returns its result without the
  asynchronous machinery's overhead.
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
os.environ.setdefault("EQX_ON_ERROR", "nan")


def compile_cache_dir(env=os.environ) -> str | None:
    """Where JAX's persistent compilation cache lives (None: off), from
    ``REELBENCH_COMPILE_CACHE`` (unset or "1": the user's cache directory; "0": off; else a path)."""
    value = env.get("REELBENCH_COMPILE_CACHE", "1").strip()
    if value.lower() in ("0", "off", "false", "no", ""):
        return None
    if value.lower() in ("1", "on", "true", "yes"):
        from reelbench.models.io import user_cache_dir

        return str(user_cache_dir(env) / "jax")
    return os.path.expanduser(value)

import jax  # noqa: E402  (after XLA_FLAGS, on purpose)

jax.config.update("jax_enable_x64", True)
if "jax_cpu_enable_async_dispatch" in jax.config.values:
    jax.config.update("jax_cpu_enable_async_dispatch", False)
_CACHE_DIR = compile_cache_dir()
if _CACHE_DIR is not None:
    jax.config.update("jax_compilation_cache_dir", _CACHE_DIR)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

import jax.numpy as jnp  # noqa: E402  (after the flag, on purpose)

#: XLA_FLAGS as JAX's backend will read them (fixed once the backend initialises).
_XLA_FLAGS_AT_IMPORT = os.environ.get("XLA_FLAGS", "")


def xla_flags() -> str:
    """The XLA_FLAGS this process's JAX runs with (for the results' provenance)."""
    return _XLA_FLAGS_AT_IMPORT


__all__ = ["jax", "jnp", "xla_flags", "append_xla_flags", "compile_cache_dir", "DEFAULT_XLA_FLAGS"]
