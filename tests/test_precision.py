"""Stored precision of drawn populations (subslope.simulation.precision)."""

from __future__ import annotations

import numpy as np
import pytest

from subslope.simulation.precision import (
    LOS_DTYPE,
    SUBHALO_DTYPES,
    rounded,
    rounded_image,
    stored,
)


def test_rounded_values_are_exactly_representable():
    v = np.random.default_rng(0).uniform(-2, 2, 1000)
    r = rounded(v, np.float16, "subhalos.x")
    assert r.dtype == np.float64
    np.testing.assert_array_equal(r.astype(np.float16).astype(np.float64), r)
    assert np.max(np.abs(r - v)) <= 2.0**-11  # half the float16 spacing on [1, 2)


def test_rounding_stays_inside_the_bounds():
    # float16(2.99) = 2.9902 and float16(1.01) = 1.0098 lie outside (1.01, 2.99)
    r = rounded([2.99, 1.01, 2.9899, 1.5], np.float16, "subhalos.gamma", (1.01, 2.99))
    assert np.all((r >= 1.01) & (r <= 2.99))
    assert r[3] == 1.5


def test_overflow_names_the_field():
    with pytest.raises(ValueError, match=r"subhalos\.mass = 1e\+40.*float32"):
        rounded([1e8, 1e40], np.float32, "subhalos.mass")
    with pytest.raises(ValueError, match="float16"):
        rounded([7e4], np.float16, "subhalos.x")


def test_stored_keeps_the_drawn_fields_only():
    arrays = {
        "counts": np.array([2]),
        "mass": np.array([2e8, 1e7]),
        "x": np.zeros(2),
        "amp": np.ones(2),
        "gamma": None,
    }
    out = stored(arrays, SUBHALO_DTYPES)
    assert set(out) == {"counts", "mass", "x"}
    assert out["mass"].dtype == np.float32 and out["x"].dtype == np.float16
    assert out["counts"].dtype == np.int64
    assert stored(arrays, LOS_DTYPE)["amp"].dtype == np.float32


def test_rounded_image_is_round_half_even_to_16_mantissa_bits():
    rng = np.random.default_rng(1)
    x = np.concatenate(
        [
            rng.normal(0, 1, 5000) * 10.0 ** rng.uniform(-6, 3, 5000),
            [0.0, -0.0, 1.0, 1 + 2.0**-17, 1 + 3 * 2.0**-17, 410.48303, -0.006560877],
        ]
    ).astype(np.float32)
    r = rounded_image(x)
    assert r.dtype == np.float32
    m, e = np.frexp(x.astype(np.float64))  # x = m 2^e, 0.5 <= |m| < 1: 24 bits in m
    reference = np.ldexp(np.rint(np.ldexp(m, 17)), e - 17)  # keep 1 + 16 bits, half to even
    np.testing.assert_array_equal(r.astype(np.float64), reference)
    assert r[-4] == 1.0 and r[-3] == 1 + 2.0**-15  # ties to even
    np.testing.assert_array_equal(rounded_image(r), r)
    assert np.all(r.view(np.uint32) & np.uint32(0x7F) == 0)
    np.testing.assert_array_equal(rounded_image(x, 23), x)
    with pytest.raises(ValueError, match="bits"):
        rounded_image(x, 0)
    for bad in (np.nan, np.inf, np.float32(3.4028235e38)):  # the last rounds up to inf
        with pytest.raises(ValueError, match="non-finite"):
            rounded_image(np.array([1.0, bad], dtype=np.float32))
