"""Wrapped fringe phase from four phase-shifted frames: 4-step and Carré estimators.

Each fringe frame of one set obeys (SCAN_BUNDLE.md)

    I_δ(p) = A(p) + B(p)·cos(ψ(p) + δ),   ψ = 2π(u·p′)/P + c,   δ ∈ {0, 90, 180, 270}°

with A = k·ρ·V·max(0, n·l)·E(p′), B = m·A (modulation m).  The phase ψ is returned wrapped to
(−π, π]; it carries the unknown per-set constant c, which the reference target's phase removes
(see :mod:`worker.recon.unwrap`).

The Digital Hammurabi paper (Kumar et al. 2003, Eq. 4) uses the Carré algorithm, which needs
four frames with equal but unknown phase step 2α: a projector whose step is not exactly 90°
(gamma, shift errors) still gives the right phase.  :func:`carre_phase` implements it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worker.recon.unwrap import wrap_phase

# Pixels per block of rows in the per-pixel passes: a few arrays of it fit the L2 cache
# (1 MiB a core here; 2¹⁶ rather than 2¹⁵: half the calls, a 4-step set 4.5 → 4.2 ms).
_BLOCK_PIXELS = 1 << 16

__all__ = [
    "CarrePhase",
    "FringePhase",
    "IntensityNoise",
    "carre_phase",
    "four_step_phase",
    "intensity_noise",
    "phase_sigma_rad",
]


@dataclass(frozen=True)
class FringePhase:
    """Output of :func:`four_step_phase`.

    phase_rad : (H, W) float32, ψ wrapped to (−π, π] (argument of the pattern at δ = 0).
    modulation : (H, W) float32, B/A (≈ m where the model holds; low in shadows, saturation,
        blur or where interreflections add unmodulated light).  NaN where A ≤ 0; None when
        not asked for.
    amplitude : (H, W) float32, B in the units of the frames.
    mean : (H, W) float32, A, the mean of the four frames.
    residual : (H, W) float32, ½·((I_0 + I_180) − (I_90 + I_270)): zero for the model, so it
        is pure noise (variance σ_I² for four frames of equal noise σ_I) plus whatever the
        model misses (saturation, harmonics, phase-step errors).  See :func:`intensity_noise`.
    """

    phase_rad: np.ndarray
    modulation: np.ndarray
    amplitude: np.ndarray
    mean: np.ndarray | None = None
    residual: np.ndarray | None = None


@dataclass(frozen=True)
class IntensityNoise:
    """Camera noise of one four-frame set: σ_I² = read_var + gain·A (photon-transfer model).

    read_var : float, variance at zero signal (read noise, quantisation), frame units².
    gain : float, variance per unit of mean level (shot noise), frame units.
    harmonic : (float, float), the pattern's second harmonic seen in the 4-step residual,
        r ≈ A·(c·cos 2ψ + s·sin 2ψ) (a projector's intensity non-linearity); (0, 0) when
        not significant.  The 4-step phase is blind to it, so it is not noise.
    """

    read_var: float
    gain: float
    harmonic: tuple[float, float] = (0.0, 0.0)

    def variance(self, mean: np.ndarray) -> np.ndarray:
        m = np.asarray(mean, dtype=np.float32)
        return np.float32(self.read_var) + np.float32(self.gain) * np.maximum(m, np.float32(0))


@dataclass(frozen=True)
class CarrePhase:
    """Output of :func:`carre_phase`.

    phase_rad : (H, W) float32, ψ of the first frame, wrapped to (−π, π] (full range), or
        known only modulo π in ``quadrant="paper"`` mode (wrapped to (−π/2, π/2]).
    modulation, amplitude : (H, W) float32, B/A and B, computed with the median step.
    step_rad : (H, W) float32, the per-pixel estimate of the phase step 2α (NaN where
        ill-conditioned: sin ψ ≈ 0 or no fringe contrast).
    median_step_rad : float, the median of ``step_rad`` over well-modulated pixels.
    """

    phase_rad: np.ndarray
    modulation: np.ndarray
    amplitude: np.ndarray
    step_rad: np.ndarray
    median_step_rad: float


def _frames(name: str, frames: np.ndarray) -> np.ndarray:
    arr = np.asarray(frames)
    if arr.ndim != 3 or arr.shape[0] != 4:
        raise ValueError(f"{name} must have shape (4, H, W), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ValueError(f"{name} must be real numeric, got dtype {arr.dtype}")
    return arr.astype(np.float32, copy=False)


def four_step_phase(
    frames: np.ndarray, *, modulation: bool = True, out: FringePhase | None = None
) -> FringePhase:
    """Standard 4-step phase shifting (δ = 0, 90, 180, 270°).

    With I_δ = A + B cos(ψ + δ): I_0 − I_180 = 2B cos ψ and I_270 − I_90 = 2B sin ψ, so
    ψ = atan2(I_270 − I_90, I_0 − I_180), B = ½·sqrt((I_270 − I_90)² + (I_0 − I_180)²),
    A = mean of the four frames.  Phase noise: σ_ψ ≈ σ_I/(√2·B) for independent frames.

    frames : (4, H, W) array in the order δ = 0, 90, 180, 270°, linear radiance (not
    flat-fielded: the phase does not depend on the scale).  modulation: False leaves B/A
    out (None), for callers that use it for some sets only.
    out : arrays to write the result into, typically those of a previous set's result that
    is no longer needed (each (H, W) float32); its None fields are allocated.  A fresh
    1.3 Mpx array costs its page faults, about as much time as all the arithmetic here.
    """
    f = _frames("frames", frames)
    rows, cols = f.shape[1:]

    def buffer(field: str) -> np.ndarray:
        given = None if out is None else getattr(out, field)
        if given is None:
            return np.empty((rows, cols), np.float32)
        if (
            given.shape != (rows, cols)
            or given.dtype != np.float32
            or not given.flags.c_contiguous  # OpenCV writes into the modulation's memory
        ):
            raise ValueError(
                f"out.{field} must be C-contiguous ({rows}, {cols}) float32, "
                f"got {given.shape} {given.dtype}"
            )
        return given

    phase, amp, mean, residual = (buffer(k) for k in ("phase_rad", "amplitude", "mean", "residual"))
    mod = buffer("modulation") if modulation else None
    # Blocks of rows that stay in the CPU cache: the dozen passes below over whole 1.3 Mpx
    # frames were bound by memory bandwidth, which the frame decoding shares (80 sets of a
    # paper scan: 0.28 → 0.22 CPU s cold, more under the decoding); same values.
    step = max(1, _BLOCK_PIXELS // max(cols, 1))
    if mod is not None:
        nan_block = np.full((min(step, rows), cols), np.nan, np.float32)
    for r0 in range(0, rows, step):
        sl = slice(r0, r0 + step)
        i0, i90, i180, i270 = f[:, sl]
        s = np.subtract(i270, i90)
        c = np.subtract(i0, i180)
        np.arctan2(s, c, out=phase[sl])
        # sqrt(s² + c²) in place: np.hypot is 3× slower and its overflow care is not needed.
        s *= s
        c *= c
        s += c
        b = np.sqrt(s, out=amp[sl])
        b *= np.float32(0.5)
        even = np.add(i0, i180, out=residual[sl])
        odd = np.add(i90, i270, out=c)
        a = np.add(even, odd, out=mean[sl])
        a *= np.float32(0.25)
        even -= odd
        even *= np.float32(0.5)
        if mod is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                m = np.divide(b, a, out=mod[sl])
            # NaN where A ≤ 0 (B/NaN is NaN already), by OpenCV's masked copy: numpy's
            # boolean assignment took 3× as long as the rest of the modulation.
            dark = np.less_equal(a, np.float32(0))
            cv2.copyTo(nan_block[: len(m)], dark.view(np.uint8), m)
    return FringePhase(phase_rad=phase, modulation=mod, amplitude=amp, mean=mean, residual=residual)


def intensity_noise(
    mean: np.ndarray,
    residual: np.ndarray,
    *,
    phase_rad: np.ndarray | None = None,
    samples: int = 20_000,
) -> IntensityNoise:
    """Fit the photon-transfer model σ_I² = read_var + gain·A to one set's 4-step residuals.

    The residual r = ½((I_0 + I_180) − (I_90 + I_270)) of :func:`four_step_phase` has variance
    σ_I² wherever the model holds, whatever the phase, so every pixel is a one-degree-of-
    freedom noise sample at its mean level A (the EMVA 1288 photon-transfer idea, with the
    fringe set as its own flat field).  Robust to the pixels where the model fails: A is cut
    into 12 quantile bins, σ² of a bin is median(r²)/0.4549 (the median of χ²₁), and a
    Theil–Sen line is fitted to the bins, both coefficients kept ≥ 0.  A regular
    grid of about ``samples`` pixels is used (the fit needs thousands, not millions).

    A pattern that is not a pure sinusoid (a projector's gamma) puts its second harmonic,
    A·h₂·cos(2ψ + ·), into r although the 4-step phase ignores it; given ``phase_rad`` the
    harmonic is fitted first (least squares on A·cos 2ψ, A·sin 2ψ) and removed when it
    lowers the median r² by more than 10 %; it is returned in ``harmonic``.

    mean, residual, phase_rad : (H, W) from :func:`four_step_phase`.
    """
    mean = np.asarray(mean, dtype=np.float32)
    stride = max(1, int(np.sqrt(mean.size / max(samples, 1))))
    a = mean[::stride, ::stride].ravel()
    r = np.asarray(residual, dtype=np.float32)[::stride, ::stride].ravel()
    ok = np.isfinite(a) & np.isfinite(r) & (a > 0)
    harmonic = (0.0, 0.0)
    if phase_rad is not None:
        psi = np.asarray(phase_rad, dtype=np.float32)[::stride, ::stride].ravel()
        ok &= np.isfinite(psi)
    a, r = a[ok].astype(np.float64), r[ok].astype(np.float64)
    if phase_rad is not None and a.size >= 24:
        x = np.stack([a * np.cos(2.0 * psi[ok]), a * np.sin(2.0 * psi[ok])], axis=1)
        coef = np.linalg.lstsq(x, r, rcond=None)[0]
        cleaned = r - x @ coef
        if np.median(cleaned**2) < 0.9 * np.median(r**2):
            r, harmonic = cleaned, (float(coef[0]), float(coef[1]))
    r2 = np.square(r)
    if a.size < 24:
        var = float(np.median(r2) / 0.4549) if a.size else 0.0
        return IntensityNoise(read_var=var, gain=0.0, harmonic=harmonic)
    order = np.argsort(a)
    xa, yv = _bin_medians(a[order], r2[order], 12)
    yv /= 0.4549
    # Theil–Sen line through the bins: a few bins spoilt by saturation or by the model's
    # failure (the brightest, the darkest) do not tilt it, as they would a least-squares fit.
    i, j = np.triu_indices(xa.size, k=1)
    dx = xa[j] - xa[i]
    keep = dx > 0
    gain = float(np.median((yv[j] - yv[i])[keep] / dx[keep])) if keep.any() else 0.0
    read_var = float(np.median(yv - gain * xa))
    if gain < 0:
        gain, read_var = 0.0, float(np.median(yv))
    elif read_var < 0:
        gain, read_var = float(np.median(yv / xa)), 0.0
    return IntensityNoise(read_var=float(read_var), gain=float(gain), harmonic=harmonic)


def _bin_medians(a_sorted, b, n_bins):
    """Medians of a_sorted and of b over the bins of np.array_split(…, n_bins) (a_sorted
    ascending): each bin's median of a is its middle value(s), those of b are taken on two
    rectangular blocks (the first bins are one longer), not bin by bin."""
    n = a_sorted.size
    size, extra = divmod(n, n_bins)
    lengths = np.array([size + 1] * extra + [size] * (n_bins - extra))
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    lo, hi = starts + (lengths - 1) // 2, starts + lengths // 2
    xa = (a_sorted[lo] + a_sorted[hi]) / 2
    cut = extra * (size + 1)
    yv = np.concatenate(
        [
            np.median(b[:cut].reshape(extra, size + 1), axis=1),
            np.median(b[cut:].reshape(n_bins - extra, size), axis=1),
        ]
    )
    return xa, yv


def phase_sigma_rad(
    phase: FringePhase,
    noise: IntensityNoise,
    *,
    local_px: int = 5,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Standard deviation of the 4-step phase, σ_ψ = σ_I/(√2·B), float32 (H, W).

    From ψ = atan2(I_270 − I_90, I_0 − I_180) with independent frame noise σ_I
    (:func:`four_step_phase`).  σ_I² is the larger of the set's photon-transfer model at the
    pixel's mean level and the local mean of the squared 4-step residual over
    ``local_px`` × ``local_px`` pixels (0: model only), less the second harmonic
    ``noise.harmonic``: the local term catches what the model misses (saturation, dark
    pixels below the fit's range, interreflections), so it only ever makes a phase less
    trusted.  inf where B = 0, NaN where the frames are.  A shadowed pixel has
    B ≈ σ_I (noise only), hence σ_ψ ≈ 0.7 rad or more: such phases never fix an order.
    out : (H, W) float32 array to write σ_ψ into (no fresh array then: see
    :func:`four_step_phase`), else one is allocated.
    """
    if phase.mean is None or phase.residual is None:
        raise ValueError("phase has no mean level or residual: use four_step_phase")
    mean = np.asarray(phase.mean, dtype=np.float32)
    rows, cols = mean.shape
    if out is None:
        out = np.empty((rows, cols), np.float32)
    elif out.shape != (rows, cols) or out.dtype != np.float32:
        raise ValueError(f"out must be ({rows}, {cols}) float32, got {out.shape} {out.dtype}")
    # Whole-frame passes: in row blocks, as four_step_phase, they were no faster (the few
    # arrays stay in the L3 cache; the blocks' calls add up); the local mean of r² is
    # formed in `out` itself.
    if local_px > 1:
        r = phase.residual
        if noise.harmonic != (0.0, 0.0):
            # The pattern's second harmonic is no noise (the 4-step phase ignores it).
            c2, s2 = noise.harmonic
            two_psi = 2.0 * phase.phase_rad
            fit = np.cos(two_psi) * np.float32(c2)
            fit += np.sin(two_psi) * np.float32(s2)
            fit *= mean
            r = np.subtract(r, fit, out=fit)
        np.square(r, out=out)
        cv2.blur(out, (local_px, local_px), dst=out, borderType=cv2.BORDER_REFLECT)
    var = np.maximum(mean, np.float32(0))
    var *= np.float32(noise.gain)
    var += np.float32(noise.read_var)
    if local_px > 1:
        # fmax: a NaN neighbourhood (undecodable pixels) falls back on the model.
        np.fmax(var, out, out=var)
    var *= np.float32(0.5)
    np.sqrt(var, out=out)
    with np.errstate(divide="ignore", invalid="ignore"):
        out /= phase.amplitude
    return out


def carre_phase(
    frames: np.ndarray,
    *,
    nominal_step_deg: float = 90.0,
    quadrant: str = "full",
) -> CarrePhase:
    """Carré phase shifting with an unknown, equal phase step (the paper's Eq. 4).

    Frames I1…I4 taken at ψ − 3α, ψ − α, ψ + α, ψ + 3α (step 2α, unknown).  With
    a = I2 − I3 = 2B sin ψ sin α, b = I1 − I4 = 2B sin ψ sin 3α and
    d = (I2 + I3) − (I1 + I4) = 4B cos ψ sin α sin 2α:

        tan ψ = sqrt((3a − b)(a + b)) / d,     tan² α = (3a − b)/(a + b).

    The square root loses the sign of sin ψ.  ``quadrant="full"`` (default) restores it from
    the signs of (I2 − I3) and (I1 − I4), which both carry the sign of sin ψ for a step below
    120° (their sum is used, as the better-conditioned of the two), and the sign of cos ψ
    from d: ψ = atan2(sign(a + b)·sqrt(|(3a − b)(a + b)|), d), a full-range (−π, π] phase.
    ``quadrant="paper"`` returns the textbook formula as written, arctan of the ratio with
    the numerator signed by (I2 − I3) (range (−π/2, π/2): ψ only modulo π), for
    :func:`worker.recon.unwrap.paper_consistent_unwrap`.

    The returned phase is that of the FIRST frame, ψ − 3α_nominal, so that with the nominal
    step it equals :func:`four_step_phase` on ideal data.  A miscalibrated step shifts it by
    the same constant 3(α − α_nominal) on the object and the reference, which cancels in
    their difference.

    frames : (4, H, W) in acquisition order (nominal δ = 0, 90, 180, 270°).
    """
    if quadrant not in ("full", "paper"):
        raise ValueError(f"quadrant must be 'full' or 'paper', got {quadrant!r}")
    if not (0.0 < float(nominal_step_deg) < 120.0):
        raise ValueError(f"nominal_step_deg must lie in (0, 120), got {nominal_step_deg}")
    i1, i2, i3, i4 = _frames("frames", frames)
    a = i2 - i3
    b = i1 - i4
    d = (i2 + i3) - (i1 + i4)
    prod = (3.0 * a - b) * (a + b)
    root = np.sqrt(np.abs(prod))
    half_nominal = 0.5 * np.deg2rad(float(nominal_step_deg))
    if quadrant == "full":
        mid = np.arctan2(np.sign(a + b) * root, d)
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            mid = np.arctan(np.sign(a) * root / d)
    cycle = 2.0 * np.pi if quadrant == "full" else np.pi
    phase = wrap_phase(mid - np.float32(3.0 * half_nominal), cycle_rad=cycle)

    with np.errstate(divide="ignore", invalid="ignore"):
        tan2 = (3.0 * a - b) / (a + b)
        step = 2.0 * np.arctan(np.sqrt(np.where(tan2 >= 0, tan2, np.nan)))
    mean = 0.25 * (i1 + i2 + i3 + i4)
    # The step is best measured where sin ψ is large relative to the noise: |a + b| big.
    # A strided sample is plenty for one global number and far cheaper than the full image.
    st_s = step[::3, ::3]
    strength = np.abs(a + b)[::3, ::3]
    fin = np.isfinite(st_s) & np.isfinite(strength)
    good = fin & (strength > (np.median(strength[fin]) if fin.any() else np.inf))
    median_step = float(np.median(st_s[good])) if good.any() else 2.0 * half_nominal
    al = 0.5 * median_step
    sin_a = np.sin(al)
    sin_3a = np.sin(3.0 * al)
    # B from the two quadratures at the median step: B sin ψ from a and b, B cos ψ from d.
    b_sin = (a * sin_a + b * sin_3a) / (2.0 * (sin_a**2 + sin_3a**2))
    b_cos = d / (4.0 * sin_a * np.sin(2.0 * al))
    amp = np.sqrt(b_sin**2 + b_cos**2)
    with np.errstate(divide="ignore", invalid="ignore"):
        mod = np.where(mean > 0, amp / mean, np.nan)
    return CarrePhase(
        phase_rad=phase.astype(np.float32),
        modulation=mod.astype(np.float32),
        amplitude=amp.astype(np.float32),
        step_rad=step.astype(np.float32),
        median_step_rad=median_step,
    )
