"""Speed of the scanner simulator: tablet, view ray casting, frame rendering.

    PYTHONPATH=. .venv/bin/python bench/bench_simulate.py [--sizes 320x256,1280x1024]

Prints CPU seconds (process time, so a busy machine does not inflate them) per step and
an estimate for a whole scan (view + all frames of the matching preset, without PNG/disk).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from worker.simulate.acquisition import PRESETS, pixel_size_for, plan_frames
from worker.simulate.noise import noise_model
from worker.simulate.rig import FrameSpec, render_frame
from worker.simulate.scan import scan_rig
from worker.simulate.tablet import FACE_POSES, make_tablet
from worker.simulate.view import render_view


def _frames_cpu(view, frames, noise, rig) -> float:
    """CPU seconds per frame for rendering ``frames`` (values only, no PNG or disk)."""
    rng = np.random.default_rng(0)
    t0 = time.process_time()
    for f in frames:
        render_frame(view, f, noise, rng, rig=rig)
    return (time.process_time() - t0) / len(frames)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", default="320x256,1280x1024")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    t0 = time.process_time()
    tablet = make_tablet(args.seed)
    t_tablet = time.process_time() - t0
    print(
        f"make_tablet: {t_tablet:.2f} s CPU, {len(tablet.wedges)} wedges, "
        f"{len(tablet.cavities)} cavities"
    )
    noise = noise_model("default")
    print(
        "| size | supersample | rays | view s | photometric s/frame | fringe s/frame | frames | scan estimate s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for text in args.sizes.split(","):
        w, h = (int(v) for v in text.split("x"))
        preset = PRESETS["paper"] if w >= 1280 else PRESETS["quick"]
        pixel = pixel_size_for(w, h)
        t0 = time.process_time()
        view = render_view(
            tablet,
            FACE_POSES["obverse"],
            width=w,
            height=h,
            pixel_size_um=pixel,
            supersample=preset.supersample,
        )
        t_view = time.process_time() - t0
        rig = scan_rig(args.seed, w, h, pixel, noise)
        photo = [FrameSpec("photometric", "object", az, 45.0) for az in (0.0, 90.0, 180.0)]
        fringe = [
            FrameSpec("fringe", "object", 0.0, 45.0, None, 3000.0, ph) for ph in (0, 90, 180, 270)
        ]
        t_photo = _frames_cpu(view, photo, noise, rig)
        t_fringe = _frames_cpu(view, fringe, noise, rig)
        frames = plan_frames(
            preset,
            width=w,
            height=h,
            pixel_size_um=pixel,
            noise=noise,
            rng=np.random.default_rng(0),
        )
        n_fringe = sum(f.kind == "fringe" for f in frames)
        estimate = t_view + (len(frames) - n_fringe) * t_photo + n_fringe * t_fringe
        print(
            f"| {w}x{h} | {preset.supersample} | {w * h * preset.supersample**2} | {t_view:.1f} "
            f"| {t_photo:.3f} | {t_fringe:.3f} | {len(frames)} | {estimate:.0f} |"
        )


if __name__ == "__main__":
    main()
