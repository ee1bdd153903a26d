"""Numerical checks shared by the profile tests: random sample points and finite differences."""

import numpy as np
import torch

F64 = torch.float64


def ring_points(rng, n=200, lo=0.3, hi=2.0):
    """``n`` float64 points with radius uniform in [lo, hi] arcsec and random angle."""
    r = rng.uniform(lo, hi, n)
    th = rng.uniform(-np.pi, np.pi, n)
    return torch.tensor(r * np.cos(th), dtype=F64), torch.tensor(r * np.sin(th), dtype=F64)


def fd_grad(f, x, y, h=1e-3):
    """Fourth-order central differences of every output of ``f(x, y)`` along x and along y."""

    def d(shift):
        fp2, fp1, fm1, fm2 = f(*shift(2 * h)), f(*shift(h)), f(*shift(-h)), f(*shift(-2 * h))
        return [(-a + 8 * b - 8 * c + e) / (12 * h) for a, b, c, e in zip(fp2, fp1, fm1, fm2)]

    return d(lambda s: (x + s, y)), d(lambda s: (x, y + s))
