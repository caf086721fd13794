"""lin(v), dark selection and L = (lin(v) − lin(v_dark)) / exposure."""

from __future__ import annotations

import numpy as np
import pytest

from worker.bundle.radiometry import linearize, radiance, select_dark


@pytest.mark.parametrize("bit_depth", [8, 10, 12, 16])
@pytest.mark.parametrize("gamma", [1.0, 0.45, 2.2])
def test_linearize_matches_the_formula(bit_depth: int, gamma: float) -> None:
    rng = np.random.default_rng(bit_depth)
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    v = rng.integers(0, 2**bit_depth, size=(9, 7), dtype=dtype)
    v[0, 0], v[0, 1] = 0, 2**bit_depth - 1
    before = v.copy()
    got = linearize(v, bit_depth=bit_depth, gamma=gamma)
    want = (v / (2.0**bit_depth - 1)) ** gamma
    assert got.dtype == np.float32 and got.shape == v.shape
    # Results lie in [0, 1]; float32 rounding is ≤ 2^-24 relative, so 1e-6 absolute bounds it.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert got[0, 0] == 0 and got[0, 1] == 1
    np.testing.assert_array_equal(v, before)


def test_float_values_are_linear_already() -> None:
    v = np.array([[0.5, -0.01], [2.0, 0.0]], np.float32)
    out = linearize(v, bit_depth=12, gamma=2.2)
    np.testing.assert_array_equal(out, v)
    out[0, 0] = 9
    assert v[0, 0] == 0.5  # a copy


def test_bad_arguments_name_the_argument() -> None:
    with pytest.raises(ValueError, match="values"):
        linearize(np.zeros((2, 2), np.int32), bit_depth=12, gamma=1)
    with pytest.raises(ValueError, match="bit_depth"):
        linearize(np.zeros((2, 2), np.uint16), bit_depth=17, gamma=1)
    with pytest.raises(ValueError, match="gamma"):
        linearize(np.zeros((2, 2), np.uint16), bit_depth=12, gamma=0)
    with pytest.raises(ValueError, match="exposure"):
        select_dark(0, [])
    with pytest.raises(ValueError, match="dark_linear"):
        radiance(np.zeros((2, 2), np.uint8), np.zeros((3, 2), np.float32),
                 bit_depth=8, gamma=1, exposure=1)  # fmt: skip


@pytest.mark.parametrize(
    ("exposure", "darks", "want"),
    [
        (1.0, [], None),
        (1.0, [(3, 1.0), (5, 1.0)], 3),  # same exposure: the first
        (1.0000005, [(3, 2.0), (5, 1.0)], 5),  # equal within 1e-6
        (2.0, [(3, 1.0), (5, 4.0)], 3),  # a tie in ratio: the shorter
        (3.0, [(5, 9.0), (3, 1.0)], 3),  # 1/3 and 3: a tie up to rounding; the shorter
        (3.0, [(3, 1.0), (5, 8.0)], 5),  # ratio 2.67 beats 3
        (0.1, [(3, 0.3), (5, 0.05)], 5),  # ratio 2 beats 3
    ],
)
def test_select_dark(exposure, darks, want) -> None:
    assert select_dark(exposure, darks) == want


def test_radiance_formula() -> None:
    v = np.array([[100, 4095]], np.uint16)
    dark = linearize(np.array([[10, 20]], np.uint16), bit_depth=12, gamma=1.0)
    got = radiance(v, dark, bit_depth=12, gamma=1.0, exposure=2.0)
    want = (np.array([[100, 4095]]) - np.array([[10, 20]])) / 4095 / 2.0
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert got.dtype == np.float32
    no_dark = radiance(v, None, bit_depth=12, gamma=1.0, exposure=1.0)
    np.testing.assert_allclose(no_dark, v / 4095, rtol=1e-6)


@pytest.mark.parametrize(
    ("dtype", "bit_depth", "gamma"),
    [(np.uint8, 8, 1.0), (np.uint16, 12, 1.0), (np.uint16, 12, 2.2), (np.float32, 12, 2.2)],
)
def test_radiance_into_out_gives_the_same_values(dtype, bit_depth: int, gamma: float) -> None:
    # out= (the measurement stages' stacks) must change where L goes, not one bit of it.
    rng = np.random.default_rng(bit_depth)
    if dtype == np.float32:
        v = rng.uniform(0, 1, (9, 7)).astype(np.float32)
    else:
        v = rng.integers(0, 2**bit_depth, size=(9, 7), dtype=dtype)
    dark = linearize(np.full((9, 7), 3, np.uint16), bit_depth=12, gamma=1.0)
    for d, exposure in ((None, 1.0), (dark, 0.5)):
        want = radiance(v, d, bit_depth=bit_depth, gamma=gamma, exposure=exposure)
        out = np.full((9, 7), np.nan, np.float32)
        got = radiance(v, d, bit_depth=bit_depth, gamma=gamma, exposure=exposure, out=out)
        assert got is out
        np.testing.assert_array_equal(out, want)
    with pytest.raises(ValueError, match="out"):
        linearize(v, bit_depth=bit_depth, gamma=gamma, out=np.empty((7, 9), np.float32))
