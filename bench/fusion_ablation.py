"""Where the default surface loses to the plain chain: its steps switched off one at a time,
and the error split into fine and coarse bands (issue 15, item 1).

    .venv/bin/python bench/fusion_ablation.py --work DIR --only NAME[,NAME...]

Reads scans simulated by `bench/robustness.py` (DIR/NAME/bundle and DIR/NAME/gt; nothing
is written there). Each bundle is measured once (`worker.measure.measure_bundle`, mask as
the pipeline's); then the default surface (`pipeline.surface_of`: fusion, band-wise
correction, sharpening; before the cliff refinement and the guard, which act off the core)
is computed as it is and with one step changed:

- `no sharpening`: the point-sample sharpening off (`fusion.sharpen_heights`);
- `sharpen psf only`: the sharpening's σ without the pixel's own area (σ_psf instead of
  √(σ_psf² + 1/12));
- `no band-wise`: the band-wise Wiener correction off (`band_wiener`);
- `no normal bias`: `normal_bias.correct_normal_bias` off;
- `no variance comp.`: `fuse_default(variance_components=False)`;
- `plain fusion`: the plain chain's fixed-weight solve (`plain.fuse_plain_um`) of the
  default's normals and fringe heights;
- `plain fusion, plain normals`: the same solve of the plain chain's least-squares normals
  and the default's fringe heights;
- `plain chain`: the plain chain's own surface (its normals, fringe heights and mask).

Figures (`worker.recon.evaluate`'s core: true mask eroded by 4 px, true slope < 60°,
median offset removed): height MAE and RMS (µm), wedge depth error (mean |error| and mean
signed error: + too deep), and the MAE of two hybrids of the error maps split at 8 px
(Gaussian scale space, `band_wiener` bands 0–8 px and ≥ 8 px): `fine→plain` = this row's
coarse error with the plain chain's fine error, `coarse→plain` = the other way round. Where
swapping in the plain chain's fine bands closes the gap, the loss lies below 8 px.
"""

from __future__ import annotations

import sys
from pathlib import Path

# Python puts this script's folder first on sys.path, where bench/queue.py would shadow the
# standard library's queue (which concurrent.futures and multiprocessing import).
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
from contextlib import nullcontext  # noqa: E402
from unittest import mock  # noqa: E402

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

import worker.pipeline as pipeline  # noqa: E402
import worker.plain_chain as plain_chain  # noqa: E402
from worker.bundle import open_bundle  # noqa: E402
from worker.measure import measure_bundle  # noqa: E402
from worker.recon.band_wiener import BAND_SCALES_PX, _bands  # noqa: E402
from worker.recon.evaluate import wedge_depth_um  # noqa: E402
from worker.recon.fusion import fuse_default, sharpen_heights  # noqa: E402
from worker.recon.plain import fuse_plain_um  # noqa: E402

SPLIT_PX = 8.0  # the fine bands are those whose coarse scale is at most this


def core_mask(gt_mask: np.ndarray, gt_normals: np.ndarray) -> np.ndarray:
    """`evaluate`'s core pixels: the true mask eroded by 4 px, true slope under 60°."""
    inner = ndimage.binary_erosion(gt_mask, structure=np.ones((3, 3), bool), iterations=4)
    return inner & (np.abs(gt_normals[..., 2]) > np.cos(np.radians(60.0)))


def error_um(height: np.ndarray, gt: np.ndarray, core: np.ndarray) -> np.ndarray:
    """Height error on the core, median offset removed; 0 elsewhere and where NaN."""
    sel = core & np.isfinite(height)
    e = np.where(sel, height - gt, 0).astype(np.float32)
    return np.where(sel, e - np.median(e[sel]), 0).astype(np.float32)


def fine_coarse(err: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The error map split into bands finer and coarser than SPLIT_PX (they sum to err on sel)."""
    bands = _bands(err, sel.astype(np.float32), BAND_SCALES_PX)
    cut = sum(1 for s in BAND_SCALES_PX[1:] if s <= SPLIT_PX)
    return sum(bands[:cut]), sum(bands[cut:])


def wedge_errors_um(height: np.ndarray, gt: np.ndarray, wedges: list, core: np.ndarray):
    """(mean |depth error|, mean signed depth error, + too deep) over the core's wedges."""
    fill = np.where(np.isfinite(height), height, np.nanmedian(height))
    d = [
        wedge_depth_um(fill, w) - wedge_depth_um(gt, w)
        for w in wedges
        if core[int(round(w["bottom"]["row"])), int(round(w["bottom"]["col"]))]
    ]
    return (float(np.mean(np.abs(d))), float(np.mean(d))) if d else (float("nan"),) * 2


def plain_inputs(bundle: Path) -> dict:
    """The plain chain's normals, fringe heights and mask (what it hands its solve) and its
    surface, from one run of the chain into a temporary folder."""
    seen: dict = {}
    solve = plain_chain.fuse_plain_um

    def spy(normals, fringe, mask, **kw):
        h = solve(normals, fringe, mask, **kw)
        seen.update(normals=normals, fringe=fringe, mask=mask, height=h)
        return h

    with tempfile.TemporaryDirectory() as tmp, mock.patch.object(plain_chain, "fuse_plain_um", spy):
        plain_chain.reconstruct_plain(bundle, Path(tmp) / "out")
    return seen


def variants(meas, mask, psf_px: float, plain: dict) -> dict[str, np.ndarray]:
    """Heights of the default surface and of each variant (module docstring)."""
    s = meas.pixel_size_um

    def surface(**patches):
        with mock.patch.multiple(pipeline, **patches) if patches else nullcontext():
            return pipeline.surface_of(meas, mask, blur_sigma_px=psf_px)[0]

    out = {"default": surface()}
    out["no sharpening"] = surface(sharpen_heights=lambda h, m, **k: h.copy())
    out["sharpen psf only"] = surface(
        sharpen_heights=lambda h, m, blur_sigma_px, **k: sharpen_heights(
            h, m, blur_sigma_px=psf_px, **k
        )
    )
    out["no band-wise"] = surface(_band_wiener=lambda meas_, h, m, **k: (h, {"ran": False}))
    out["no normal bias"] = surface(correct_normal_bias=lambda n, f, **k: n)
    out["no variance comp."] = surface(
        fuse_default=lambda *a, **k: fuse_default(*a, **k, variance_components=False)
    )
    out["plain fusion"] = fuse_plain_um(meas.normals, meas.fringe_height_um, mask, pixel_size_um=s)
    out["plain fusion, plain normals"] = fuse_plain_um(
        plain["normals"], meas.fringe_height_um, mask, pixel_size_um=s
    )
    out["plain chain"] = plain["height"]
    return out


def run_scan(folder: Path) -> list[tuple]:
    """Rows (variant, MAE, RMS, wedge MAE, wedge signed, fine→plain, coarse→plain)."""
    bundle = folder / "bundle"
    gt = np.load(folder / "gt" / "height.npy")
    core = core_mask(np.load(folder / "gt" / "mask.npy"), np.load(folder / "gt" / "normals.npy"))
    wedges_path = folder / "gt" / "wedges.json"
    wedges = json.loads(wedges_path.read_text())["wedges"] if wedges_path.exists() else []
    with open_bundle(bundle) as b:
        meas = measure_bundle(b, progress=lambda stage, fraction: None)
        meas.finish()
        psf_px = pipeline.camera_psf(b.manifest)[0]
    mask = pipeline._mask(meas)
    plain = plain_inputs(bundle)
    heights = variants(meas, mask, psf_px, plain)
    sel = core.copy()
    for h in heights.values():
        sel &= np.isfinite(h)
    ref_fine, ref_coarse = fine_coarse(error_um(plain["height"], gt, sel), sel)

    def mae(e):
        v = e[sel]
        return float(np.mean(np.abs(v - np.median(v))))

    rows = []
    for name, h in heights.items():
        e = error_um(h, gt, sel)
        fine, coarse = fine_coarse(e, sel)
        w_abs, w_signed = wedge_errors_um(h, gt, wedges, core)
        rows.append(
            (
                name,
                mae(e),
                float(np.sqrt(np.mean(np.square(e[sel])))),
                w_abs,
                w_signed,
                mae(ref_fine + coarse),
                mae(fine + ref_coarse),
            )
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="bench/robustness.py's cache")
    ap.add_argument("--only", required=True, help="comma-separated scan names")
    args = ap.parse_args(argv)
    for name in [n for n in args.only.split(",") if n]:
        folder = args.work / name
        if not (folder / "bundle" / "manifest.json").exists():
            print(f"{name}: no bundle under {folder}", file=sys.stderr)
            return 2
        print(f"\n#### {name} ({int(core_mask_size(folder))} core pixels)\n")
        print(
            "| variant | MAE µm | RMS µm | wedge µm | wedge signed µm "
            "| MAE, fine→plain | MAE, coarse→plain |"
        )
        print("|---|---:|---:|---:|---:|---:|---:|")
        for row in run_scan(folder):
            print(f"| {row[0]} | " + " | ".join(f"{v:.2f}" for v in row[1:]) + " |")
    return 0


def core_mask_size(folder: Path) -> int:
    return int(
        core_mask(np.load(folder / "gt" / "mask.npy"), np.load(folder / "gt" / "normals.npy")).sum()
    )


if __name__ == "__main__":
    sys.exit(main())
