"""Symmetric LGVI (docs/equations.md, "The symmetric LGVI") and its fourth-order compositions.

The paper's LGVI (`integrators.lgvi`) evaluates the s_p-dependent mass terms and
the forcing at the left end of the step, which makes it first order while the string is
reeled. ``lgvi_sym`` evaluates the mass terms at the step midpoint and every force once at the
midpoint with the secant velocity: the forced discrete map is self-adjoint, so second order
everywhere. It is the same step, structured solver and lifecycle as ``lgvi``; only the
discrete Lagrangian differs (`integrators._lgvi_core.DiscreteLagrangian(symmetric=True)`), and
at fixed length without axial damping it is the same computation as ``lgvi``.

Because the step is symmetric, compositions Φ_{γ_m h} ∘ … ∘ Φ_{γ_1 h} with the classical
coefficients raise it to order 4 (Yoshida 1990 triple jump; Suzuki 1990 five stages). They
differ only by the coefficients `YOSHIDA4` / `SUZUKI4`; one step of size h costs 3 or 5
symmetric substeps. Suzuki's substeps are all |γ_i| ≤ 0.66 (Yoshida's reach 1.70 h, with a
backward one), so at the same h it is both more accurate and more stable per step.
"""

from __future__ import annotations

from reelbench.integrators.lgvi import LGVI, Scheme
from reelbench.integrators.registry import register

_CBRT2, _CBRT4 = 2.0 ** (1.0 / 3.0), 4.0 ** (1.0 / 3.0)
#: Yoshida's triple jump: γ1 = γ3 = 1/(2 − 2^{1/3}), γ2 = 1 − 2 γ1 (≈ 1.3512, −1.7024, 1.3512)
YOSHIDA4 = (1.0 / (2.0 - _CBRT2), 1.0 - 2.0 / (2.0 - _CBRT2), 1.0 / (2.0 - _CBRT2))
#: Suzuki's fractal: γ1 = γ2 = γ4 = γ5 = 1/(4 − 4^{1/3}), γ3 = 1 − 4 γ1 (≈ 0.4145 ×4, −0.6580)
_S = 1.0 / (4.0 - _CBRT4)
SUZUKI4 = (_S, _S, 1.0 - 4.0 * _S, _S, _S)


@register
class LGVISym(LGVI):
    name = "lgvi_sym"
    order = 2
    orders = None  # the same order at fixed length and while reeling (the paper's lgvi: 2 and 1)
    scheme = Scheme(symmetric=True)
    description = "symmetric LGVI: midpoint mass terms and forcing, second order while reeling"


# The compositions differ from lgvi_sym only by their coefficients (and what follows from them).
@register
class LGVIYoshida4(LGVISym):
    name = "lgvi_yoshida4"
    order = 4
    scheme = Scheme(symmetric=True, gammas=YOSHIDA4)
    cost_hint = (30.0, 0.9)
    description = "Yoshida triple-jump composition of the symmetric LGVI: order 4, 3 substeps per step"


@register
class LGVISuzuki4(LGVISym):
    name = "lgvi_suzuki4"
    order = 4
    scheme = Scheme(symmetric=True, gammas=SUZUKI4)
    cost_hint = (30.0, 1.5)
    description = "Suzuki 5-stage composition of the symmetric LGVI: order 4, 5 substeps per step"
