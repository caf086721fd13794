"""Photometric stereo on synthetic shading with known normals, under light sets and BRDFs
our simulator does not make (DiLiGenT-like 96-light grid, rings at mixed polar angles,
three and four lights; Blinn–Phong and Torrance–Sparrow lobes, dark albedo, an ambient
term, cast shadows of bumps), against two oracles on the same noisy data: least squares
over the true Lambertian inliers of noise-only data ("oracle") and over the truly clean
samples of the actual data ("clean-oracle", lobe below 8 % + 3σ).

    .venv/bin/python bench/photometric_synthetic.py [name filters...]

Prints one line per case: median / mean / p90 / p99 angular error (degrees), the NaN rate
where ≥ 3 lights are lit, the NaN rate where fewer are (must be 1), CPU seconds.
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from worker.recon.photometric import light_directions, photometric_stereo  # noqa: E402
from worker.simulate.shadow import cast_shadow  # noqa: E402


def scene(size=128, px=20.0, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(float) * px
    c = (size - 1) / 2 * px
    R = 0.42 * size * px
    rr2 = (xx - c) ** 2 + (yy - c) ** 2
    inside = rr2 < (R * 0.98) ** 2
    zc = np.sqrt(np.clip(R**2 - rr2, 1e-9, None))
    h = np.where(inside, zc, 0.0)
    gx = np.where(inside, -(xx - c) / zc, 0.0)
    gy = np.where(inside, -(yy - c) / zc, 0.0)
    # small Gaussian bumps on the plane (cast shadows, varied normals)
    for _ in range(10):
        bx, by = rng.uniform(0, size * px, 2)
        s = rng.uniform(2, 5) * px
        a = rng.uniform(0.5, 1.5) * s
        g = a * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * s * s))
        g = np.where(inside, 0, g)
        h = h + g
        gx = gx + g * -(xx - bx) / s**2
        gy = gy + g * -(yy - by) / s**2
    n = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    # exclude the silhouette rim where sphere meets plane (normals discontinuous)
    rim = np.abs(np.sqrt(rr2) - R * 0.98) < 2 * px
    return h, n, ~rim


def lights_diligent():
    # 8 x 12 grid of directions on the plane z=-1, like DiLiGenT's 96 LEDs
    xs = np.linspace(-0.8, 0.8, 12)
    ys = np.linspace(-0.6, 0.6, 8)
    X, Y = np.meshgrid(xs, ys)
    d = np.stack([X.ravel(), Y.ravel(), -np.ones(X.size)], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def lights_rings(polars, per):
    az, po = [], []
    for i, p in enumerate(polars):
        a = np.arange(per) * 360 / per + i * 360 / per / len(polars)
        az += list(a)
        po += [p] * per
    return light_directions(az, po)


def to_az_polar(ls):
    polar = np.degrees(np.arccos(-ls[:, 2]))
    az = np.degrees(np.arctan2(ls[:, 0], ls[:, 1]))
    return az, polar


def render(h, n, ls, rho, brdf, px=20.0, ambient=0.0):
    az, polar = to_az_polar(ls)
    cos = np.einsum("hwc,kc->khw", n, ls)
    V = np.stack([cast_shadow(h, px, a, max(p, 0.5)) for a, p in zip(az, polar, strict=True)])
    v = np.array([0, 0, -1.0])
    half = ls + v
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    nh = np.clip(np.einsum("hwc,kc->khw", n, half), 0, 1)
    nv = np.clip(-n[..., 2], 1e-3, 1)[None]
    lam = rho[None] * np.clip(cos, 0, None)
    spec = np.zeros_like(lam)
    kind = brdf[0]
    if kind == "bp":
        _, ks, alpha = brdf
        spec = ks * nh**alpha * (cos > 0)
    elif kind == "ts":
        _, ks, m = brdf
        # Torrance-Sparrow / Cook-Torrance: Beckmann D, Schlick F, Cook G; radiance f·(n·l)
        c2 = np.clip(nh, 1e-3, 1) ** 2
        D = np.exp((c2 - 1) / (c2 * m * m)) / (np.pi * m * m * c2 * c2)
        vh = np.clip(np.einsum("kc,c->k", half, v), 1e-3, 1)[:, None, None]
        F = 0.04 + 0.96 * (1 - vh) ** 5
        cl = np.clip(cos, 1e-3, None)
        G = np.minimum(1, np.minimum(2 * nh * nv / vh, 2 * nh * cl / vh))
        spec = ks * F * D * G / (4 * nv) * (cos > 0)
    amb = ambient * rho[None] * np.ones_like(lam)
    s = V * (lam + spec) + amb
    return s, cos, V, spec


def angerr(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def run(name, ls, brdf, rho, noise_rel=0.01, seed=1, ambient=0.0, **kw):
    h, n, keep = scene()
    rng = np.random.default_rng(seed)
    s, cos, V, spec = render(h, n, ls, rho, brdf, ambient=ambient)
    # shot-like noise: sigma = noise_rel * sqrt(s * 0.5) + read
    sig = noise_rel * np.sqrt(np.clip(s, 0, None) * 0.5 + 1e-4)
    sn = (s + rng.normal(size=s.shape) * sig).astype(np.float32)
    t0 = time.process_time()
    res = photometric_stereo(sn, ls, **kw)
    cpu = time.process_time() - t0
    e = angerr(res.normals, n)
    good = (cos > 0.1) & V
    ok3 = keep & (good.sum(0) >= 3)
    nan = np.mean(~np.isfinite(e[ok3]))
    few = keep & (((cos > 0) & V).sum(0) < 3)
    nan_few = np.mean(~np.isfinite(e[few])) if few.any() else np.nan
    # oracle: LS on Lambertian-only noisy samples on the true inliers
    lam = (rho[None] * np.clip(cos, 0, None) + rng.normal(size=s.shape) * sig).astype(float)
    w = good.astype(float)
    A = np.einsum("khw,ki,kj->hwij", w, ls, ls)
    bvec = np.einsum("khw,khw,ki->hwi", w, lam, ls)
    A = np.where(ok3[..., None, None], A, np.eye(3))
    b = np.linalg.solve(A, bvec[..., None])[..., 0]
    no = b / np.linalg.norm(b, axis=-1, keepdims=True)
    eo = angerr(no, n)
    # selection oracle: LS over the truly clean samples of the actual data
    clean = good & (spec * V < 0.08 * rho[None] * np.clip(cos, 0, None) + 3 * sig)
    okc = keep & (clean.sum(0) >= 3)
    w = clean.astype(float)
    A = np.einsum("khw,ki,kj->hwij", w, ls, ls)
    bvec = np.einsum("khw,khw,ki->hwi", w, sn.astype(float), ls)
    A = np.where(okc[..., None, None], A, np.eye(3)) + 1e-9 * np.eye(3)
    b = np.linalg.solve(A, bvec[..., None])[..., 0]
    nc = b / np.linalg.norm(b, axis=-1, keepdims=True)
    ec = angerr(nc, n)[okc]
    ecl = e[okc]
    ecl = ecl[np.isfinite(ecl)]
    ee = e[ok3]
    ee = ee[np.isfinite(ee)]
    print(
        f"{name:34s} K={len(ls):3d} med {np.median(ee):6.2f} mean {np.mean(ee):6.2f} "
        f"p90 {np.percentile(ee, 90):6.2f} p99 {np.percentile(ee, 99):6.2f} | oracle med "
        f"{np.median(eo[ok3]):5.2f} mean {np.mean(eo[ok3]):5.2f} | nan {nan:.4f} "
        f"nan(<3) {nan_few:.3f} cpu {cpu:.2f} | clean-oracle {np.mean(okc[keep]):.2f} med {np.median(ec):5.2f} p90 {np.percentile(ec, 90):5.2f}; ours there med {np.median(ecl):5.2f} p90 {np.percentile(ecl, 90):5.2f}",
        flush=True,
    )
    return res


if __name__ == "__main__":
    size = 128
    rng = np.random.default_rng(0)
    rho_var = rng.uniform(0.3, 0.9, (size, size))
    rho_dark = np.full((size, size), 0.04)
    dil = lights_diligent()
    ring16 = light_directions(np.arange(16) * 22.5, 45.0)
    mixed = lights_rings([15, 35, 55, 70], 8)
    which = sys.argv[1:] or ["all"]
    cases = [
        ("ring16 lambert", ring16, ("lam",), rho_var),
        ("ring16 bp0.5^50", ring16, ("bp", 0.5, 50), rho_var),
        ("ring16 bp0.25^20", ring16, ("bp", 0.25, 20), rho_var),
        ("dil96 lambert", dil, ("lam",), rho_var),
        ("dil96 bp0.5^50", dil, ("bp", 0.5, 50), rho_var),
        ("dil96 bp1^10", dil, ("bp", 1.0, 10), rho_var),
        ("dil96 bp2^200", dil, ("bp", 2.0, 200), rho_var),
        ("dil96 ts3 m0.2", dil, ("ts", 3.0, 0.2), rho_var),
        ("dil96 ts3 m0.4", dil, ("ts", 3.0, 0.4), rho_var),
        ("dil96 dark bp0.2^50", dil, ("bp", 0.2, 50), rho_dark),
        ("dil96 dark bp0.3^300", dil, ("bp", 0.3, 300), rho_dark),
        ("dil96 lambert ambient0.05", dil, ("lam",), rho_var, 0.05),
        ("mixed32 lambert", mixed, ("lam",), rho_var),
        ("mixed32 bp0.5^30", mixed, ("bp", 0.5, 30), rho_var),
        ("mixed32 ts3 m0.3", mixed, ("ts", 3.0, 0.3), rho_var),
        ("three lights lambert", light_directions([0, 120, 240], [30, 45, 60]), ("lam",), rho_var),
        ("four lights lambert", light_directions([0, 90, 180, 270], 40), ("lam",), rho_var),
        ("four lights bp0.5^50", light_directions([0, 90, 180, 270], 40), ("bp", 0.5, 50), rho_var),
    ]
    for c in cases:
        if which != ["all"] and not any(w in c[0] for w in which):
            continue
        amb = c[4] if len(c) > 4 else 0.0
        run(c[0], c[1], c[2], c[3], ambient=amb)
