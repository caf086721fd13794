"""Reconstruction benchmark: speed, memory and accuracy of the four surfaces.

    .venv/bin/python bench/reconstruct.py [--preset paper] [--seeds 0,1,2] [--noise default]
                                          [--size WxH] [--physics-seed N] [--work DIR]
                                          [--no-speed]
                                          [--no-accuracy] [--no-cli | --cli-only] [--repeat 3]

For each seed: simulate a scan (worker.simulate; kept in --work to be reused), then
1. decode: the time to decode every image of the bundle to radiance (the floor), in a child
   process;
2. the whole pipeline (`reconstruct_bundle`, default fusion) in a child process: time per
   stage, total, and the child's peak resident memory (VmHWM, see below);
   both `--repeat` times, alternating which runs first; the table gives medians;
   unless --no-cli, also issue 15's own figure: the CLI `python -m worker.reconstruct
   BUNDLE OUT --quiet` from process start to exit (imports and the model directory's
   writing included: wall, CPU and peak RSS of that process by os.wait4) against a fresh
   process that imports the bundle reader and decodes every image (the same decode);
3. accuracy (worker.recon.evaluate) and fusion time (wall and CPU) of the four surfaces:
   fringe heights alone (5×5 median), normals integrated alone, the paper's fusion, the
   default fusion (sharpened by the camera blur measured on the bundle, then its cliff
   pixels set to their area mean by `pipeline.refine_walls`), with the wedge depth error
   split into its rim and bottom parts (signed means, median offset removed: + is too
   high, so a bottom at +2 and a rim at 0 is a wedge 2 µm too shallow).
With several seeds, a summary table (mean and worst over the seeds) closes the output.
Prints markdown tables (docs/benchmarks.md keeps the last run), each as soon as its runs end
(flushed: the CLI's figure comes last, minutes after the in-process table on a loaded
machine). Every run's figures are printed; the tables give the largest peak RSS. A peak RSS
is that of the measured program alone: Linux hands a child the parent's peak as its own
ru_maxrss when it execs (the old address space's high-water mark is kept; with vfork that is
the parent's, so a bench that simulated its scan gave every child the simulation's 1.8 GB).
So the in-process children read their VmHWM (the peak of the address space since exec), and
the CLI and decode processes are started by a small launcher process (`_LAUNCH`) whose own
peak, ~15 MB, is all they inherit; it times them by os.wait4.
Model directories of the speed runs go to a temporary folder, never into --work (which may be
a shared cache).
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
import multiprocessing as mp  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from worker.bundle import open_bundle  # noqa: E402
from worker.measure import measure_bundle  # noqa: E402
from worker.pipeline import (  # noqa: E402
    _mask,
    camera_blur_px,
    reconstruct_bundle,
    refine_walls,
    surface_of,
)
from worker.recon.evaluate import evaluate  # noqa: E402
from worker.simulate import simulate_scan  # noqa: E402

SURFACES = [
    ("fringe heights alone (5×5 median)", "default", "fringe"),
    ("normals integrated alone", "default", "normals"),
    ("paper fusion (Kumar 2003)", "paper", "fused"),
    ("default fusion (weighted LSQ)", "default", "fused"),
]


def simulate(
    work: Path, *, seed: int, preset: str, noise: str, size, physics_seed: int | None = None
) -> Path:
    """The scan of ``seed`` in ``work`` (simulated once); ``physics_seed``: the instrument's
    physics drawn at random (`--physics random`, as bench/robustness.py's scans), else ideal."""
    tag = f"{preset}-{noise}-s{seed}" + (f"-{size[0]}x{size[1]}" if size else "")
    if physics_seed is not None:
        tag += f"-random{physics_seed}"
    out = work / tag
    if not (out / "gt").exists():
        physics = "ideal" if physics_seed is None else "random"
        simulate_scan(
            out,
            seed=seed,
            preset=preset,
            noise=noise,
            size=size,
            physics=physics,
            physics_seed=physics_seed,
        )
    return out


def _peak_rss_mib() -> float:
    """Peak resident memory of this process's own address space (VmHWM), MiB; not
    ru_maxrss, which also holds the parent's peak when this process was started (Linux)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) for ln in f if ln.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration):  # not Linux: ru_maxrss (KiB), an upper bound
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _decode_child(bundle_path, queue):
    with open_bundle(bundle_path) as b:
        frames = [f for f in b.frames if f.kind != "dark"]
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(0, len(frames), 8):
            b.radiance_many(frames[i : i + 8])
        queue.put((time.perf_counter() - t0, time.process_time() - c0, len(frames)))


def decode_time(bundle_path: Path) -> tuple[float, float, int]:
    """Wall and CPU seconds to decode every image to radiance, 8 at a time in threads, in a
    fresh process like the pipeline's run (same start-up state for both)."""
    return _in_child(_decode_child, str(bundle_path))


def _child(bundle_path, out_dir, queue):
    t0, c0 = time.perf_counter(), time.process_time()
    report = reconstruct_bundle(bundle_path, out_dir)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    queue.put(
        {"timings": report["timings_s"], "wall": wall, "cpu": cpu, "maxrss_mib": _peak_rss_mib()}
    )


def _in_child(target, *args):
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def pipeline_run(bundle_path: Path, out_dir: Path) -> dict:
    return _in_child(_child, str(bundle_path), str(out_dir))


# The decode floor as a process of its own, start to exit: the same decode as `_decode_child`
# (every non-dark image to radiance, 8 at a time), after importing only the bundle reader.
_DECODE_SCRIPT = """
import sys
from worker.bundle import open_bundle
with open_bundle(sys.argv[1]) as b:
    frames = [f for f in b.frames if f.kind != "dark"]
    for i in range(0, len(frames), 8):
        b.radiance_many(frames[i : i + 8])
"""


# Starts the command of its arguments and prints its wall, CPU (user + system) seconds and
# peak RSS, start to exit (os.wait4: that child's own figures). A process of its own so that
# the command inherits its small peak RSS, not the bench's (see the module's docstring).
_LAUNCH = """
import json, os, subprocess, sys, time
t0 = time.perf_counter()
proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)
_, status, usage = os.wait4(proc.pid, 0)
wall = time.perf_counter() - t0
print(json.dumps({"wall": wall, "cpu": usage.ru_utime + usage.ru_stime,
                  "maxrss_mib": usage.ru_maxrss / 1024,
                  "exit": os.waitstatus_to_exitcode(status)}))
"""


def _process_run(args: list[str]) -> dict:
    """Wall, CPU (user + system) seconds and peak RSS (MiB) of one process, start to exit."""
    done = subprocess.run(
        [sys.executable, "-c", _LAUNCH, *args], cwd=_HERE.parent, capture_output=True
    )
    if done.returncode != 0:
        raise RuntimeError(f"launcher exited {done.returncode}: {done.stderr.decode()[-2000:]}")
    run = json.loads(done.stdout)
    if run.pop("exit") != 0:
        raise RuntimeError(f"{args[1:3]} failed: {done.stderr.decode()[-2000:]}")
    return run


def cli_speed(bundle_path: Path, repeat: int) -> tuple[list[dict], list[dict]]:
    """`repeat` runs each of the decode process and of `python -m worker.reconstruct`,
    alternating which goes first (as `speed`)."""
    decodes, runs = [], []
    for i in range(repeat):
        with tempfile.TemporaryDirectory(prefix="bench-model-") as tmp:
            cli = [sys.executable, "-m", "worker.reconstruct", str(bundle_path), tmp + "/m"]
            dec = [sys.executable, "-c", _DECODE_SCRIPT, str(bundle_path)]
            if i % 2 == 0:
                decodes.append(_process_run(dec))
            runs.append(_process_run([*cli, "--quiet"]))
            if i % 2 == 1:
                decodes.append(_process_run(dec))
    return decodes, runs


def _print_cli_speed(decodes: list[dict], runs: list[dict]) -> None:
    med = np.median
    wall, dec = med([r["wall"] for r in runs]), med([d["wall"] for d in decodes])
    cpu, dec_cpu = med([r["cpu"] for r in runs]), med([d["cpu"] for d in decodes])
    rss, dec_rss = max(r["maxrss_mib"] for r in runs), max(d["maxrss_mib"] for d in decodes)
    each = ", ".join(
        f"{r['wall']:.2f}/{d['wall']:.2f} s, {r['cpu']:.1f}/{d['cpu']:.1f} CPU s, "
        f"{r['maxrss_mib']:.0f}/{d['maxrss_mib']:.0f} MiB"
        for r, d in zip(runs, decodes, strict=True)
    )
    print(
        f"\nCLI, process start to exit (`python -m worker.reconstruct … --quiet` against a "
        f"process that decodes every image): {wall:.2f} s / {dec:.2f} s = {wall / dec:.2f} "
        f"(wall, medians); CPU seconds {cpu:.1f} / {dec_cpu:.1f} = {cpu / dec_cpu:.2f}; "
        f"peak RSS {rss:.0f} MiB (decode {dec_rss:.0f} MiB)\n"
        f"runs (CLI / decode): {each}",
        flush=True,
    )


def speed(bundle_path: Path, repeat: int) -> tuple[list[tuple[float, float, int]], list[dict]]:
    """`repeat` decode runs and `repeat` pipeline runs, alternating which goes first: a run
    straight after the other one's heavy I/O and allocation is slower, and alternating
    spreads that evenly over both instead of favouring either."""
    decodes, runs = [], []
    for i in range(repeat):
        with tempfile.TemporaryDirectory(prefix="bench-model-") as tmp:
            if i % 2 == 0:
                decodes.append(decode_time(bundle_path))
            runs.append(pipeline_run(bundle_path, Path(tmp) / "model"))
            if i % 2 == 1:
                decodes.append(decode_time(bundle_path))
    return decodes, runs


def _wedge_parts(h, gt_h, wedges, inner, sel) -> tuple[float, float]:
    """Mean signed rim and bottom height errors (µm) at the evaluated wedges, after removing
    the median height offset (the same offset as worker.recon.evaluate)."""
    from scipy import ndimage

    offset = float(np.median((h - gt_h)[sel])) if sel.any() else 0.0
    h_fill = np.where(np.isfinite(h), h, np.nanmedian(h))
    rims, bottoms = [], []
    for w in wedges:
        b = w["bottom"]
        r, c = int(round(b["row"])), int(round(b["col"]))
        if not (0 <= r < inner.shape[0] and 0 <= c < inner.shape[1]) or not inner[r, c]:
            continue

        def at(a, p):
            return float(ndimage.map_coordinates(a, [[p["row"]], [p["col"]]], order=1)[0])

        rims.append(np.mean([at(h_fill, p) - at(gt_h, p) for p in w["rim"]]) - offset)
        bottoms.append(at(h_fill, b) - at(gt_h, b) - offset)
    return (float(np.mean(rims)), float(np.mean(bottoms))) if rims else (np.nan, np.nan)


def accuracy(sim: Path) -> tuple[list[dict], float]:
    from scipy import ndimage

    gt = {k: np.load(sim / "gt" / f"{k}.npy") for k in ("height", "normals", "mask")}
    wedges = json.loads((sim / "gt" / "wedges.json").read_text())["wedges"]
    with open_bundle(sim / "bundle") as b:
        meas = measure_bundle(b, progress=lambda s, f: None)
        blur = camera_blur_px(b)
    mask = _mask(meas)
    inner = ndimage.binary_erosion(gt["mask"], structure=np.ones((3, 3), bool), iterations=4)
    slope_ok = np.abs(gt["normals"][..., 2]) > np.cos(np.radians(60.0))
    rows = []
    for label, fusion, surface in SURFACES:
        t0, c0 = time.perf_counter(), time.process_time()
        h, n, _ = surface_of(meas, mask, fusion=fusion, surface=surface, blur_sigma_px=blur)
        if (fusion, surface) == ("default", "fused"):  # as reconstruct_bundle does
            h = refine_walls(meas, h, mask, blur_sigma_px=blur)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        m = mask & np.isfinite(h)
        figs = evaluate(
            h,
            n,
            m,
            gt_height_um=gt["height"],
            gt_normals=gt["normals"],
            gt_mask=gt["mask"],
            wedges=wedges,
        )
        rim, bottom = _wedge_parts(h, gt["height"], wedges, inner, inner & slope_ok & m)
        rows.append(
            {"surface": label, "time_s": dt, "cpu_s": dc, "rim_um": rim, "bottom_um": bottom} | figs
        )
    return rows, blur


def _summary(per_seed: dict[int, list[dict]]) -> None:
    print(f"\n### Summary over seeds {sorted(per_seed)} (mean / worst)\n")
    print(
        "| surface | coverage | height MAE µm | height RMS µm | normal median ° "
        "| wedge depth MAE µm |\n|---|---|---|---|---|---|"
    )
    labels = [r["surface"] for r in next(iter(per_seed.values()))]
    for i, label in enumerate(labels):
        seed_rows = [rows[i] for rows in per_seed.values()]

        def stat(key, worst=max, scale=1.0, fmt=".2f", seed_rows=seed_rows):
            v = [scale * r[key] for r in seed_rows]
            return f"{np.mean(v):{fmt}} / {worst(v):{fmt}}"

        print(
            f"| {label} | {stat('coverage', min, 100)} % | {stat('height_mae_um')} "
            f"| {stat('height_rms_um')} | {stat('normal_median_deg')} "
            f"| {stat('wedge_depth_mae_um')} |"
        )


def _print_speed(seed: int, decodes: list, runs: list[dict]) -> None:
    """Median of each figure over the runs (the table), and every run's total / decode."""
    med = np.median
    nframes = decodes[0][2]
    dec, dec_cpu = med([d[0] for d in decodes]), med([d[1] for d in decodes])
    print(f"\n### Speed and memory, seed {seed} ({nframes} images, median of {len(runs)} runs)\n")
    print("| stage | seconds |\n|---|---|")
    for k in runs[0]["timings"]:
        # The colour stage runs in a thread beside mask, fusion and walls.
        label = (
            "color (background: decodes its frames, overlaps mask to walls)" if k == "color" else k
        )
        print(f"| {label} | {med([r['timings'].get(k, np.nan) for r in runs]):.2f} |")
    print(f"| decode only (all images) | {dec:.2f} |")
    total = med([r["timings"]["total"] for r in runs])
    cpu = med([r["cpu"] for r in runs])
    rss = max(r["maxrss_mib"] for r in runs)
    each = ", ".join(
        f"{r['timings']['total']:.2f}/{d[0]:.2f} s, {r['maxrss_mib']:.0f} MiB"
        for r, d in zip(runs, decodes, strict=True)
    )
    print(
        f"\ntotal / decode = {total / dec:.2f} (wall, medians); CPU seconds: pipeline {cpu:.1f}, "
        f"decode {dec_cpu:.1f} (ratio {cpu / dec_cpu:.2f}); peak RSS {rss:.0f} MiB"
        f"\nruns (total / decode, peak RSS of the run): {each}",
        flush=True,
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--noise", default="default")
    p.add_argument("--seeds", default="0")
    p.add_argument("--size", default=None, help="WIDTHxHEIGHT (default: the preset's)")
    p.add_argument(
        "--physics-seed",
        type=int,
        default=None,
        help="simulate with random instrument physics drawn from this seed (default: ideal)",
    )
    p.add_argument("--work", default=None, help="folder for simulated scans (kept)")
    p.add_argument("--no-speed", action="store_true", help="accuracy table only")
    p.add_argument("--no-accuracy", action="store_true", help="speed table only")
    p.add_argument(
        "--no-cli", action="store_true", help="no CLI runs (process start to exit) in the speed"
    )
    p.add_argument(
        "--cli-only",
        action="store_true",
        help="speed: the CLI and decode processes only (issue 15's figure), no in-process runs",
    )
    p.add_argument(
        "--repeat", type=int, default=3, help="decode and pipeline runs for the speed table"
    )
    args = p.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x")) if args.size else None
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-recon-"))
    work.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    per_seed: dict[int, list[dict]] = {}
    physics = "ideal" if args.physics_seed is None else f"random (seed {args.physics_seed})"
    print(
        f"preset {args.preset}, noise {args.noise}, seeds {seeds}, size {size or 'preset'},"
        f" physics {physics}"
    )
    for seed in seeds:
        sim = simulate(
            work,
            seed=seed,
            preset=args.preset,
            noise=args.noise,
            size=size,
            physics_seed=args.physics_seed,
        )
        if not args.no_speed:
            if not args.cli_only:
                _print_speed(seed, *speed(sim / "bundle", args.repeat))
            if not args.no_cli or args.cli_only:
                _print_cli_speed(*cli_speed(sim / "bundle", args.repeat))
        if args.no_accuracy:
            continue
        rows, blur = accuracy(sim)
        per_seed[seed] = rows
        print(f"\n### Accuracy, seed {seed} (camera blur measured: σ = {blur:.3f} px)\n")
        print(
            "| surface | coverage | height MAE µm | height RMS µm | normal median ° "
            "| wedge depth MAE µm | rim / bottom µm | surface wall s | CPU s |"
            "\n|---|---|---|---|---|---|---|---|---|"
        )
        for r in rows:
            print(
                f"| {r['surface']} | {100 * r['coverage']:.2f} % | {r['height_mae_um']:.2f} "
                f"| {r['height_rms_um']:.2f} | {r['normal_median_deg']:.2f} "
                f"| {r['wedge_depth_mae_um']:.2f} ({r['wedges']}) "
                f"| {r['rim_um']:+.2f} / {r['bottom_um']:+.2f} | {r['time_s']:.2f} "
                f"| {r['cpu_s']:.2f} |"
            )
    if len(per_seed) > 1:
        _summary(per_seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
