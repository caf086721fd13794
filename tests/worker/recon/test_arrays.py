"""Shared array primitives (worker.recon.arrays) against numpy's own results."""

import numpy as np
import pytest


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("size", [1, 2, 4095, 4096, 4097, 100_000, 100_001])
def test_fast_median_is_numpys_bit_for_bit(dtype, size):
    # Both signs over many binades, ties, ±0, subnormals, ±inf, NaN: the radix select finds
    # the same middle values as np.partition, and the mean of the two as np.median takes it.
    from worker.recon.arrays import fast_median

    rng = np.random.default_rng(size)
    spread = rng.lognormal(0, 3, size).astype(dtype)
    ties = rng.choice(np.array([0.0, 1.0, 2.5, 2.5000002], dtype), size)
    special = spread.copy()
    special[rng.random(size) < 0.3] = 0
    special[rng.random(size) < 0.05] = np.inf
    special[rng.random(size) < 0.05] = np.finfo(dtype).smallest_subnormal
    narrow = (1 + rng.random(size) * 1e-6).astype(dtype)  # one bucket of the histogram
    signed = spread * rng.choice(np.array([-1, 1], dtype), size)
    zeros = np.where(rng.random(size) < 0.5, dtype(0), -spread)  # the median is ±0
    zeros[rng.random(size) < 0.2] = -0.0
    with_nan = signed.copy()
    with_nan[size // 2] = np.nan
    for values in (spread, ties, special, narrow, signed, -special, zeros, with_nan):
        got = fast_median(values)
        expected = np.median(values)
        assert got.dtype == expected.dtype
        assert got.tobytes() == expected.tobytes() or (np.isnan(got) and np.isnan(expected))
    strided = fast_median(spread[::3])
    assert strided.tobytes() == np.median(spread[::3]).tobytes()


@pytest.mark.parametrize(
    ("shape", "dtype"), [((3, 5, 7), np.float32), ((4, 9), np.int16), ((1, 1), np.float32)]
)
def test_copy_where_is_numpys_masked_copy(shape, dtype):
    from worker.recon.arrays import copy_where

    rng = np.random.default_rng(5)
    src = rng.normal(0, 9, shape).astype(dtype)
    dst = rng.normal(0, 9, shape).astype(dtype)
    mask = rng.random(shape) < 0.5
    expected = dst.copy()
    np.copyto(expected, src, where=mask)
    copy_where(dst, src, mask)
    np.testing.assert_array_equal(dst, expected)


def test_copy_where_refuses_a_destination_it_cannot_write_in_place():
    from worker.recon.arrays import copy_where

    dst = np.zeros((6, 8), np.float32)[:, ::2]
    with pytest.raises(ValueError, match="C-contiguous"):
        copy_where(dst, np.ones((6, 4), np.float32), np.ones((6, 4), bool))
