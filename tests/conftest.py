"""Shared test setup: float64 JAX (set once in models._jax) and small shared fixtures."""

import numpy as np
import pytest

from reelbench import models  # noqa: F401  (enables float64 before any test touches JAX)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
