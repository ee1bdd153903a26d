"""The EPL member table and pair function, and the fast float32 power they use.

:func:`epl_table` computes, once per member, the ellipse frame, the ₂F₁ series
coefficients and the prefactors of the elliptical power law (Tessore & Metcalf 2015);
:func:`epl_pair` evaluates one (point, member) pair from those rows with a single power
``R^{-t}`` (:func:`power`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from subslope.physics.profiles.ellipse import ellipse_frame
from subslope.physics.profiles.epl import R_MIN, series_coefficients

__all__ = ["epl_table", "epl_pair", "power"]


def _chebyshev_fit(fn, lo: float, hi: float, degree: int) -> tuple[tuple[int, int], ...]:
    """Monomial coefficients (lowest first) of the least-squares fit of ``fn`` at 400
    Chebyshev points of ``[lo, hi]`` (float64; within a few % of the minimax error), as
    exact integer ratios: under ``torch.compile(dynamic=True)`` a module-level float
    becomes a graph input (wrapped in a tensor on every call), an ``int / int`` folds to
    a literal (as in :mod:`subslope.physics.pairs.nfw`)."""
    t = np.cos(np.pi * (np.arange(400) + 0.5) / 400)
    xs = 0.5 * (hi + lo) + 0.5 * (hi - lo) * t
    return tuple(
        float(c).as_integer_ratio() for c in np.polynomial.polynomial.polyfit(xs, fn(xs), degree)
    )


_SQRT_HALF = math.sqrt(0.5)
#: ``log2(1 + x) / x`` on ``x ∈ [√½ − 1, √2 − 1]``, degree 7: relative error 1.7e-7.
_LOG2_COEF = _chebyshev_fit(
    lambda x: np.log2(1 + x) / np.where(x == 0, 1, x) + (x == 0) / math.log(2),
    _SQRT_HALF - 1,
    math.sqrt(2) - 1,
    7,
)
#: ``2^f`` on ``f ∈ [−1/2, 1/2]``, degree 5: relative error 1.0e-7.
_EXP2_COEF = _chebyshev_fit(lambda f: 2.0**f, -0.5, 0.5, 5)


def _horner(x: Tensor, coef: tuple[tuple[int, int], ...]) -> Tensor:
    c = [n / d for n, d in coef]
    acc = c[-2] + x * c[-1]
    for v in c[-3::-1]:
        acc = v + x * acc
    return acc


def power(r2: Tensor, ex) -> Tensor:
    """``r2 ** ex`` for normal ``r2 > 0`` and ``ex·log2(r2)`` within ±126.

    float64 (the reference path): ``exp(ex·ln r2)``. float32: without library calls:
    ``r2 = 2^k m`` with ``m ∈ [√½, √2)`` read from the bits, ``log2 m`` and ``2^f`` (the
    fraction of ``y = ex·log2 r2``) by the polynomials :data:`_LOG2_COEF` /
    :data:`_EXP2_COEF`, and ``2^round(y)`` written into the exponent bits. Relative
    error ≤ 3e-7 plus the float32 rounding of ``y`` (as for ``exp``/``log``); measured
    against float64 in ``tests/test_fast_paths.py``. The EPL pair clamps ``r2`` at
    ``R_MIN²`` = 1e-18, so ``r2`` is never zero, subnormal or negative.
    """
    if r2.dtype != torch.float32:
        return torch.exp(ex * torch.log(r2))
    i = r2.view(torch.int32) + (0x3F800000 - 0x3F3504F3)
    k = ((i >> 23) - 127).to(torch.float32)
    x = ((i & 0x7FFFFF) + 0x3F3504F3).view(torch.float32) - 1.0
    y = ex * (k + x * _horner(x, _LOG2_COEF))
    n = torch.round(y)
    scale = ((n.to(torch.int32) + 127) << 23).view(torch.float32)
    return _horner(y - n, _EXP2_COEF) * scale


def epl_table(p: dict[str, Tensor], n_terms: int) -> Tensor:
    """EPL member table ``(b, 11 + n_terms - 1, N)`` from ``(b, N)`` parameters
    ``amp, gamma, e1, e2, x, y`` (see :mod:`subslope.physics.profiles.epl`).

    Rows: ``cx, cy, q·cos φ, q·sin φ, cos φ, sin φ, −f, f², −t/2,
    2/(1+q)·A q^{t/2}, (3−γ)/2·A q^{t/2}, a_1 … a_{n−1}`` with ``t = γ − 1``,
    ``f = (1−q)/(1+q)`` and ``a_k`` the ₂F₁ series coefficients (TM15 eq. 29).
    """
    gamma, amp = p["gamma"], p["amp"]
    q, c, s = ellipse_frame(p["e1"], p["e2"])
    t = gamma - 1
    f = (1 - q) / (1 + q)
    amp_q = amp * torch.pow(q, 0.5 * t)
    rows = [
        p["x"],
        p["y"],
        q * c,
        q * s,
        c,
        s,
        -f,
        f * f,
        -0.5 * t,
        (2 / (1 + q)) * amp_q,
        (0.5 * (3 - gamma)) * amp_q,
    ]
    rows += series_coefficients(gamma, n_terms)[1:]
    return torch.stack(rows, -2)


def epl_pair(x: Tensor, y: Tensor, rows: Sequence[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    r"""EPL ``(alpha_x, alpha_y, kappa)`` of members at points from :func:`epl_table` rows.

    Same mathematics as :func:`subslope.physics.profiles.epl.epl_deflection_and_convergence`
    (Tessore & Metcalf 2015, eqs. 13, 29; Goertzel evaluation of the series at the
    complex point ``u = −f Z²/R²``), with ``R^{−t} = exp(−t/2 · ln R²)``. The number
    of series terms is ``len(rows) − 10``. Rows broadcast against ``x, y``.
    """
    cx, cy, qc, qs, c, s, mf, m, ex, sa, sk = rows[:11]
    a = rows[11:]
    dx, dy = x - cx, y - cy
    X = qc * dx + qs * dy
    Y = c * dy - s * dx
    R2 = torch.clamp(X * X + Y * Y, min=R_MIN * R_MIN)
    inv = 1.0 / R2
    ur = (X * X - Y * Y) * (mf * inv)
    if a:
        s2 = 2 * ur
        b1, b2 = a[-1] + 0 * ur, torch.zeros_like(ur)
        for k in range(len(a) - 2, -1, -1):
            b1, b2 = a[k] + s2 * b1 - m * b2, b1
        Fr = 1 + ur * b1 - m * b2
        Fi = (X * Y) * (2 * mf * inv) * b1
    else:
        Fr, Fi = torch.ones_like(ur), torch.zeros_like(ur)
    rp = power(R2, ex)
    sc = sa * rp
    axf = sc * (X * Fr - Y * Fi)
    ayf = sc * (X * Fi + Y * Fr)
    return c * axf - s * ayf, s * axf + c * ayf, sk * rp
