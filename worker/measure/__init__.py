"""Measurement stages 1–5 driven from a bundle: photometric normals, colour, fringe heights.

Streams the frames: each fringe set of four phases with its reference set is decoded in
threads while the previous one is processed, in float32, and dropped once reduced; the
photometric frames (and the colour frames, unless the colour stage runs in the background,
where it decodes its own) are decoded meanwhile, in one more thread, so that neither core
waits while the other computes. Calls the pure functions of `worker.recon`.
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from worker.measure.frames import single_threaded_blas
from worker.measure.fringe import measure_fringes
from worker.measure.photometric import decode_with_references, measure_color, measure_photometric
from worker.measure.result import Measurements, ReconstructionError
from worker.recon.color import linear_to_srgb8

__all__ = ["Measurements", "ReconstructionError", "measure_bundle"]


def measure_bundle(
    bundle, *, progress: Callable[[str, float], None], color_in_background: bool = False
) -> Measurements:
    """Run stages 1–5 on an open `worker.bundle.Bundle`.

    color_in_background: the colour stage, whose only product is the albedo texture, runs
    in a thread, decoding its frames there, and outlives the call: the bundle must stay open
    until `Measurements.finish()` has waited for it.  Meanwhile its fields (rgb_linear, its
    warnings and `used` entries) are not there yet.
    """
    man = bundle.manifest
    cam = man.camera
    meas = Measurements(pixel_size_um=float(cam.pixel_size_um), shape=(cam.height, cam.width))
    meas.scan_info = {
        "id": man.scan.id,
        "face": man.scan.face,
        # scan.pose initialises the registration of a tablet's scans (worker.register).
        "pose": None if man.scan.pose is None else [list(map(float, r)) for r in man.scan.pose],
        # scan.tablet free metadata: the designation, and whether the scan is simulated.
        "tablet": dict(man.scan.tablet),
    }
    obj = [f for f in bundle.frames if f.target == "object"]
    counts: dict[str, int] = defaultdict(int)
    for f in bundle.frames:
        counts[f.kind if f.target == "object" else f"reference_{f.kind}"] += 1
    meas.used["frames"] = dict(counts)
    rho_ref = float(man.reference.reflectance)
    fringe = [f for f in obj if f.kind == "fringe"]
    photo = [f for f in obj if f.kind == "photometric"]
    color = [f for f in obj if f.kind == "color"]
    workers = min(4, os.cpu_count() or 1)

    background = ThreadPoolExecutor(max_workers=1) if color_in_background else None
    with single_threaded_blas(), ThreadPoolExecutor(max_workers=1) as pool:
        # Colour needs normals, so it is decoded only with at least 3 photometric frames.
        jobs: dict = {}

        def decode_photometric() -> None:
            # Once every fringe frame is queued: the fringe stage's last groups and its
            # unwrapping and consensus leave a core idle, which this decoding fills (started
            # with the fringe stage it slowed its decoding down instead).
            if jobs or len(photo) < 3:
                return
            jobs["photo"] = pool.submit(decode_with_references, bundle, photo)
            if color and background is None:
                jobs["color"] = pool.submit(decode_with_references, bundle, color)

        t0 = time.perf_counter()
        progress("fringe", 0.02)
        if fringe:
            measure_fringes(
                bundle,
                fringe,
                meas,
                rho_ref,
                progress,
                workers=workers,
                on_queued=decode_photometric,
            )
        decode_photometric()
        photo_stacks, color_stacks = jobs.get("photo"), jobs.get("color")
        meas.timings["fringe"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        progress("photometric", 0.55)
        if photo_stacks is not None:
            stacks = photo_stacks.result()
            photo_stacks = None  # the frames are dropped once reduced
            measure_photometric(bundle, photo, meas, rho_ref, stacks=stacks, workers=workers)
            del stacks
        elif photo:
            meas.warnings.append(
                f"photometric: {len(photo)} object frame(s), at least 3 are needed; "
                "normals not computed"
            )
        meas.timings["photometric"] = time.perf_counter() - t0

        if meas.normals is None and meas.fringe_height_um is None:
            raise ReconstructionError(
                "bundle: nothing to reconstruct (needs ≥ 3 photometric object frames or fringe "
                "sets with reference frames); frames found: "
                + (", ".join(f"{k}={v}" for k, v in sorted(counts.items())) or "none")
            )

        progress("color", 0.75)
        if color and background is not None and meas.normals is not None:
            # Its frames are decoded there too: in the fringe stage's last seconds both cores
            # are busy, while the photometric fit and the fusion leave one partly idle.
            meas.pending.append(
                background.submit(_color, bundle, color, meas, rho_ref, None, encode=True)
            )
        elif color:
            stacks = color_stacks.result() if color_stacks is not None else None
            _color(bundle, color, meas, rho_ref, stacks)
        color_stacks = None
    if background is not None:
        background.shutdown(wait=False)
    return meas


def _color(bundle, color, meas, rho_ref, stacks, encode=False) -> None:
    # No BLAS limit here: in the background it would outlive measure_bundle's and reset it
    # when done; the colour stage calls no BLAS (recon.color).
    t0 = time.perf_counter()
    measure_color(bundle, color, meas, rho_ref, stacks=stacks)
    if encode and meas.rgb_linear is not None:
        meas.rgb_srgb8 = linear_to_srgb8(meas.rgb_linear)
    meas.timings["color"] = time.perf_counter() - t0
