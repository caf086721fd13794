"""Integration of normals: round trips on analytic surfaces (worker.recon.integrate)."""

import numpy as np
import pytest

from worker.recon.integrate import integrate_normals, slopes_from_normals

S_UM = 20.0


def _normals_of(gx, gy):
    """Unit normals n ∝ (−∂h/∂x, −∂h/∂y, −1) (SCAN_BUNDLE.md), from slopes."""
    n = np.stack([-gx, -gy, -np.ones_like(gx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def _quadric(rows=96, cols=128):
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64) * S_UM
    a, b, c, d, e = 2e-4, -1.5e-4, 1e-4, 0.3, -0.2
    h = a * x**2 + b * y**2 + c * x * y + d * x + e * y
    gx = 2 * a * x + c * y + d
    gy = 2 * b * y + c * x + e
    return h, gx, gy


def _ellipse(rows, cols):
    y, x = np.mgrid[0:rows, 0:cols]
    return ((x - cols / 2) / (0.45 * cols)) ** 2 + ((y - rows / 2) / (0.42 * rows)) ** 2 < 1


def test_slopes_follow_the_spec_sign_convention():
    gx = np.full((2, 3), 0.5)
    gy = np.full((2, 3), -0.25)
    sx, sy = slopes_from_normals(_normals_of(gx, gy))
    np.testing.assert_allclose(sx, gx, rtol=1e-6)
    np.testing.assert_allclose(sy, gy, rtol=1e-6)


def test_quadric_is_recovered_on_a_ragged_mask():
    # The trapezoid rule (mean of the two end slopes times s) is exact for a quadric, whose
    # slopes are linear: the only error left is the solver's (relative residual 1e-5 of
    # heights of ~500 µm, i.e. well under 0.05 µm).
    h, gx, gy = _quadric()
    mask = _ellipse(*h.shape)
    mask[40:44, 10:60] = False  # a notch: the mask is not convex
    got = integrate_normals(_normals_of(gx, gy), pixel_size_um=S_UM, mask=mask)
    assert np.all(np.isnan(got[~mask]))
    err = got[mask] - h[mask]
    err -= err.mean()
    assert np.max(np.abs(err)) < 0.05
    assert abs(float(np.mean(got[mask]))) < 1e-3


def test_noisy_normals_give_bounded_error_and_inputs_are_untouched():
    # Slope noise σ_g per pixel integrates like a 2-D random walk whose height variance grows
    # as σ_h² ≈ (s·σ_g)²·ln(N)/π (Green's function of the Laplacian): for σ_g = 0.01, s = 20 µm,
    # N ≈ 10⁴ pixels, σ_h ≈ 0.34 µm; the 6σ bound of the largest deviation is ~2 µm.
    rng = np.random.default_rng(3)
    h, gx, gy = _quadric()
    mask = _ellipse(*h.shape)
    n = _normals_of(gx + rng.normal(0, 0.01, gx.shape), gy + rng.normal(0, 0.01, gy.shape))
    n_copy = n.copy()
    got = integrate_normals(n, pixel_size_um=S_UM, mask=mask)
    np.testing.assert_array_equal(n, n_copy)
    err = got[mask] - h[mask]
    err -= err.mean()
    assert np.sqrt(np.mean(err**2)) < 0.34 * 2
    assert np.max(np.abs(err)) < 2.0


def test_two_islands_each_have_zero_mean():
    h, gx, gy = _quadric()
    mask = np.zeros(h.shape, bool)
    mask[10:40, 10:50] = True
    mask[60:90, 70:120] = True
    got = integrate_normals(_normals_of(gx, gy), pixel_size_um=S_UM, mask=mask)
    assert abs(float(np.mean(got[10:40, 10:50]))) < 1e-3
    assert abs(float(np.mean(got[60:90, 70:120]))) < 1e-3
    err = got[60:90, 70:120] - h[60:90, 70:120]
    assert np.ptp(err) < 0.05


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        (
            {"normals": np.zeros((4, 4)), "pixel_size_um": 1.0, "mask": np.ones((4, 4), bool)},
            "normals",
        ),
        (
            {"normals": np.zeros((4, 4, 3)), "pixel_size_um": 0.0, "mask": np.ones((4, 4), bool)},
            "pixel_size_um",
        ),
        (
            {"normals": np.zeros((4, 4, 3)), "pixel_size_um": 1.0, "mask": np.ones((3, 4), bool)},
            "mask",
        ),
    ],
)
def test_bad_input_names_the_argument(kwargs, culprit):
    with pytest.raises(ValueError, match=culprit):
        integrate_normals(kwargs.pop("normals"), **kwargs)


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("block_px", [7, 40, 10_000])
def test_operator_in_row_blocks_is_the_whole_frame_formula(monkeypatch, workers, block_px):
    # A·h = λh + Dxᵀ Wx Dx h + Dyᵀ Wy Dy h, summed in this order per pixel whatever the blocks.
    from worker.recon import integrate

    rng = np.random.default_rng(3)
    rows, cols = 23, 9
    h = rng.normal(size=(rows, cols)).astype(np.float32)
    wx = rng.random((rows, cols - 1)).astype(np.float32)
    wy = rng.random((rows - 1, cols)).astype(np.float32)
    lam = rng.random((rows, cols)).astype(np.float32)
    expected = lam * h
    ex = wx * (h[:, 1:] - h[:, :-1])
    expected[:, 1:] += ex
    expected[:, :-1] -= ex
    ey = wy * (h[1:] - h[:-1])
    expected[1:] += ey
    expected[:-1] -= ey
    monkeypatch.setattr(integrate, "_APPLY_BLOCK_PX", block_px)
    np.testing.assert_array_equal(integrate._apply(h, wx, wy, lam, workers), expected)


def test_solver_inputs_are_cleaned_like_nan_to_num():
    # Targets, data and start heights: NaN → 0 and ±inf → the largest float32 where kept,
    # 0 where their weight is 0; finite inputs pass unchanged.
    from worker.recon.integrate import _clean_into

    values = np.array([[1.5, np.nan, np.inf], [-np.inf, 2.0, np.nan]], np.float64)
    keep = np.array([[True, True, True], [True, False, False]])
    expected = np.where(keep, np.nan_to_num(values.astype(np.float32)), np.float32(0))
    out = np.zeros((2, 3), np.float32)
    _clean_into(out, values, keep)
    np.testing.assert_array_equal(out, expected)
    _clean_into(out, values)
    np.testing.assert_array_equal(out, np.nan_to_num(values.astype(np.float32)))
    finite = np.arange(6, dtype=np.float32).reshape(2, 3)
    _clean_into(out, finite)
    np.testing.assert_array_equal(out, finite)


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("block_px", [1, 20, 10_000])
def test_solver_inputs_in_row_blocks_are_the_padded_cleaned_inputs(monkeypatch, workers, block_px):
    # Every input once into the solver's copy on the DCT-friendly grid: the pad is 0, the
    # rows of every block (and the y-edges on their borders) cleaned as whole frames would be.
    from scipy import fft

    from worker.recon import integrate

    rng = np.random.default_rng(4)
    rows, cols = 23, 17  # padded to 24 × 18
    tx = rng.normal(size=(rows, cols - 1))
    ty = rng.normal(size=(rows - 1, cols))
    wx = rng.random((rows, cols - 1)).astype(np.float32) * (rng.random((rows, cols - 1)) < 0.8)
    wy = rng.random((rows - 1, cols)).astype(np.float32) * (rng.random((rows - 1, cols)) < 0.8)
    data = rng.normal(size=(rows, cols))
    lam = rng.random((rows, cols)).astype(np.float32) * (rng.random((rows, cols)) < 0.8)
    x0 = rng.normal(size=(rows, cols))
    for a in (tx, ty, data, x0):
        a[rng.random(a.shape) < 0.1] = np.nan
    tx[0, 0], ty[-1, -1] = np.inf, -np.inf
    fast = (fft.next_fast_len(rows, real=True), fft.next_fast_len(cols, real=True))
    assert fast != (rows, cols)

    def padded(a, keep=None):
        a = np.nan_to_num(a.astype(np.float32))
        if keep is not None:
            a = np.where(keep, a, np.float32(0))
        return np.pad(a, ((0, fast[0] - rows), (0, fast[1] - cols)))

    expected = (
        padded(tx, wx > 0),
        padded(ty, wy > 0),
        padded(wx),
        padded(wy),
        padded(lam),
        padded(data, lam > 0),
        padded(x0),
    )
    monkeypatch.setattr(integrate, "_PREPARE_BLOCK_PX", block_px)
    got = integrate._solver_inputs(tx, ty, wx, wy, data, lam, x0, workers=workers)
    for a, b in zip(got, expected, strict=True):
        assert a.dtype == np.float32
        np.testing.assert_array_equal(a, b)
    none = integrate._solver_inputs(tx, ty, wx, wy, None, None, None, workers=workers)
    for a in none[4:]:
        np.testing.assert_array_equal(a, np.zeros(fast, np.float32))
