"""The plugin contract: what a plugin integrator or effect must pass."""
