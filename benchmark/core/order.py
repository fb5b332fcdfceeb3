"""The observed order of convergence, stated once: p in error ∝ h^p.

``h`` is whatever shrinks toward the exact solution: the step size, 1 / steps for an adaptive
method's tolerance sweep. Two readings of one ladder of (h, error) points:

* `successive_orders`: the slope between each two successive points, log of the error ratio
  over log of the size ratio (log2 of the error ratio of a halving), as DiffEqDevTools
  computes it. The order ladders take the last halving above the reference's floor
  (`benchmark.studies.orders`), the drift check the mean over its sweep
  (`benchmark.runs.metrics.observed_orders`), the contract the last pair of its steps.
* `fitted_order`: the least-squares slope of log error against log h over the whole ladder,
  where the points are not a controlled halving (an adaptive method's tolerance sweep in the
  contract, `benchmark.contract.verify`).

Numpy only: the command line and every layer may import it.
"""

from __future__ import annotations

import numpy as np


def successive_orders(sizes, errors) -> np.ndarray:
    """The observed order between each two successive points of the ladder ``sizes`` (h, in any
    direction) and ``errors``: log(e_k / e_k+1) / log(h_k / h_k+1), one fewer than the points."""
    e, h = np.asarray(errors, float), np.asarray(sizes, float)
    return np.log(e[:-1] / e[1:]) / np.log(h[:-1] / h[1:])


def last_order(sizes, errors) -> float:
    """The observed order of the last two points (`successive_orders`' last); NaN with fewer."""
    return float(successive_orders(sizes, errors)[-1]) if len(errors) >= 2 else float("nan")


def fitted_order(sizes, errors) -> float:
    """The least-squares slope of log error against log h over every point; NaN unless the
    points hold two sizes or more."""
    h, e = np.asarray(sizes, float), np.asarray(errors, float)
    return float(np.polyfit(np.log(h), np.log(e), 1)[0]) if len(set(h.tolist())) > 1 else float("nan")
