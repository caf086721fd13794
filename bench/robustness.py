"""Robustness bench: the default reconstruction against the plain chain on scans it was not
tuned on (issue 14, build 4; the bench issue 15 is judged with).

    .venv/bin/python bench/robustness.py [--quick] [--work DIR] [--json FILE] [--jobs N]
                                         [--chains default,plain] [--only NAME,...]
                                         [--instruments native,mitsuba]
                                         [--mitsuba-tree DIR]

Scans (`SCANS`, 25; `--quick`: the 6 marked quick): random instrument physics from our
simulator (`python -m worker.simulate --physics random --physics-seed N`, 256×192), the
paper-like rig at 1280×1024, the native `default`/`hard` presets at 512×384, and scans
rendered by the second instrument (`--renderer mitsuba`, 256×192; `--mitsuba-tree`: taken
from another source tree's simulator). Each scan is simulated once into `--work` (a scan
whose bundle and gt are there is not simulated again; a folder holding only part of them
is simulated afresh, so two runs must not share `--work` at the same time) and
reconstructed by each chain with `python -m worker.reconstruct BUNDLE OUT --fusion CHAIN`
in a child process, timed from process start to exit (model directories go to a temporary
folder, deleted after evaluation).

Figures (worker.recon.evaluate, core pixels: gt mask eroded by 4 px, true slope < 60°,
median offset removed): coverage, output pixels outside the true mask (`extra`, a fraction
of the true mask: support taken for tablet), height MAE, RMS, p99.9 and max |error|, normal
median and mean error, wedge depth error; and two spike counts over every output pixel:
`spk f` = pixels whose height is more than 50 µm from the chain's own fringe heights
(quality/fringe_disagreement_um; issue 15's max(5σ_fringe, 50 µm) with σ unknown, as the
model directory does not carry it), `spk gt` = pixels of the true mask more than 50 µm
from the truth. Prints Markdown tables (per scan; median and worst per chain; on how many
scans the default is worse than the plain chain by more than 10 %) and writes everything
as JSON (`--json`, default WORK/robustness.json).
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
import math  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from worker.recon.evaluate import evaluate  # noqa: E402

SPIKE_UM = 50.0
SLACK = 1.10  # "worse" means more than 10 % worse (issue 15's slack for noise)


@dataclass(frozen=True)
class Scan:
    """One bench scan: its folder name under --work and the simulator's arguments."""

    name: str
    instrument: str  # "native" or "mitsuba"
    args: tuple[str, ...]
    quick: bool = False
    note: str = ""


def _native_random(seed: int, quick: bool = False) -> Scan:
    return Scan(
        f"native-random-{seed}",
        "native",
        ("--seed", str(seed), "--physics", "random", "--physics-seed", str(seed))
        + ("--size", "256x192"),
        quick,
    )


def _mitsuba(seed: int, quick: bool = False) -> Scan:
    return Scan(
        f"mitsuba-{seed}",
        "mitsuba",
        ("--renderer", "mitsuba", "--seed", str(seed), "--size", "256x192"),
        quick,
    )


SCANS: tuple[Scan, ...] = (
    *(_native_random(s, quick=s < 3) for s in range(16)),
    Scan(
        "native-paper-like",
        "native",
        ("--preset", "paper", "--physics", "paper-like", "--seed", "0"),
        quick=True,
        note="1280×1024, 26.8 µm: 10-bit, projector pixels, defocus, light in the clay",
    ),
    Scan("native-default-512", "native", ("--preset", "paper", "--size", "512x384", "--seed", "1")),
    Scan(
        "native-hard-512",
        "native",
        ("--preset", "paper", "--size", "512x384", "--seed", "1", "--noise", "hard"),
    ),
    *(_mitsuba(s, quick=s < 2) for s in range(6)),
)


def _child(tree: Path | None) -> dict:
    """subprocess.run's arguments for a simulator child that imports `tree`'s `worker`
    package, if given: run in the tree (`python -m` puts the working directory first on
    sys.path, before PYTHONPATH, so this tree's own package would win from here)."""
    if tree is None:
        return {}
    path = os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p)
    return {"cwd": str(tree), "env": os.environ | {"PYTHONPATH": path}}


def simulator_options(python: str, tree: Path | None = None) -> set[str]:
    """The options `python -m worker.simulate` offers (its --help)."""
    out = subprocess.run(
        [python, "-m", "worker.simulate", "--help"],
        capture_output=True,
        text=True,
        check=True,
        **_child(tree),
    ).stdout
    return {w.strip("[],") for w in out.split() if w.startswith(("--", "[--"))}


def simulate(scan: Scan, work: Path, python: str, tree: Path | None = None) -> Path:
    """The scan's folder (bundle/ and gt/), simulated unless both are there already."""
    out = work / scan.name
    if (out / "bundle" / "manifest.json").exists() and (out / "gt" / "height.npy").exists():
        return out
    if out.exists():  # an interrupted simulation: start afresh
        shutil.rmtree(out)
    cmd = [python, "-m", "worker.simulate", "--out", str(out), *scan.args]
    run = subprocess.run(cmd, capture_output=True, text=True, **_child(tree))
    if run.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {run.returncode}: {run.stderr.strip()[-500:]}")
    return out


def reconstruct(bundle: Path, out: Path, chain: str, python: str) -> tuple[int, float, str]:
    """(exit status, wall seconds from process start to exit, stderr's last line)."""
    t0 = time.perf_counter()
    run = subprocess.run(
        [python, "-m", "worker.reconstruct", str(bundle), str(out), "--fusion", chain, "--quiet"],
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - t0
    lines = [ln for ln in run.stderr.strip().splitlines() if ln.strip()]
    return run.returncode, seconds, (lines[-1] if lines else "")


def figures(sim: Path, model: Path) -> dict:
    """Accuracy of the model directory against the scan's ground truth."""
    gt = {k: np.load(sim / "gt" / f"{k}.npy") for k in ("height", "normals", "mask")}
    wedges_path = sim / "gt" / "wedges.json"
    wedges = json.loads(wedges_path.read_text())["wedges"] if wedges_path.exists() else []
    height = np.load(model / "height.npy")
    with Image.open(model / "mask.png") as im:
        mask = np.asarray(im) == 255
    figs = evaluate(
        height,
        np.load(model / "normals.npy"),
        mask & np.isfinite(height),
        gt_height_um=gt["height"],
        gt_normals=gt["normals"],
        gt_mask=gt["mask"],
        wedges=wedges,
        spike_um=SPIKE_UM,
    )
    disagreement = model / "quality" / "fringe_disagreement_um.npy"
    if disagreement.exists():
        d = np.load(disagreement)
        figs["fringe_spikes"] = int(np.count_nonzero(np.abs(d[np.isfinite(d)]) > SPIKE_UM))
    else:
        figs["fringe_spikes"] = None
    return figs


def physics_summary(sim: Path, scan: Scan) -> str:
    """The instrument's departures from the ideal one, in a few words (gt/physics.json)."""
    path = sim / "gt" / "physics.json"
    extra = [a for a in scan.args if a in ("default", "hard")]
    if not path.exists():
        return f"{scan.instrument}" + (f", noise {extra[0]}" if extra else "")
    doc = json.loads(path.read_text())
    if "physics" not in doc:  # the Mitsuba renderer records its scene instead
        clay = doc.get("clay") or {}
        bits = [f"{doc.get('renderer', scan.instrument)} {doc.get('spp', '?')} spp"]
        if "max_depth" in (doc.get("integrator") or {}):
            bits.append(f"depth {doc['integrator']['max_depth']}")
        if clay:
            bits.append(
                f"{clay.get('model', 'clay')} α {clay.get('alpha', float('nan')):.2g} "
                f"spec {clay.get('specular', float('nan')):.2g}"
            )
        return ", ".join(bits + [f"noise {extra[0]}"] if extra else bits)
    p = doc["physics"]
    out = []
    if doc.get("renderer"):  # a renderer that also records its scene (Mitsuba)
        clay = doc.get("clay") or {}
        out.append(f"{doc['renderer']} {doc.get('spp', '?')} spp")
        if clay:
            out.append(f"{clay.get('model', 'clay')} α {clay.get('alpha', float('nan')):.2g}")

    def add(cond, text):  # text is a function: its fields may be None when cond is false
        if cond:
            out.append(text())

    add(p.get("bit_depth"), lambda: f"{p['bit_depth']} bit")
    add(p.get("response_gamma") not in (None, 1.0), lambda: f"γ {p['response_gamma']:.2g}")
    add(
        p.get("psf_sigma_px") is not None,
        lambda: f"psf {p['psf_sigma_px']:.2g}" + (" (cal)" if p.get("psf_calibrated") else ""),
    )
    add(p.get("projector_defocus_um"), lambda: f"defocus {p['projector_defocus_um']:.0f} µm")
    add(
        p.get("projector_pixel_um"),
        lambda: f"proj px {p['projector_pixel_um']:.0f} µm/{p.get('projector_levels')} lv",
    )
    add(p.get("projector_gamma") not in (None, 1.0), lambda: f"proj γ {p['projector_gamma']:.2g}")
    add(p.get("phase_step_error_deg"), lambda: f"step err {p['phase_step_error_deg']:.2g}°")
    add(
        p.get("subsurface_um"),
        lambda: f"sss {p['subsurface_um']:.0f} µm×{p.get('subsurface_fraction', 1):.2g}",
    )
    lobes = p.get("specular_lobes") or []
    add(lobes, lambda: "spec " + "+".join(f"{w:.2g}/{e:.0f}" for w, e in lobes))
    add(p.get("interreflection"), lambda: f"interrefl {p['interreflection']:.2g}")
    add(p.get("veil"), lambda: f"veil {p['veil']:.2g}")
    add(p.get("albedo_scale") not in (None, 1.0), lambda: f"albedo ×{p['albedo_scale']:.2g}")
    add(p.get("hot_pixel_fraction"), lambda: "hot px")
    add(p.get("object_exposure") or p.get("reference_exposure"), lambda: "exposures")
    add(p.get("support") not in (None, "velvet"), lambda: str(p["support"]))
    add(p.get("shape") not in (None, "standard"), lambda: str(p["shape"]))
    return ", ".join(out) or p.get("name", "ideal")


@dataclass
class Result:
    scan: Scan
    physics: str = ""
    pixel_size_um: float | None = None
    size: str = ""
    error: str | None = None
    chains: dict = field(default_factory=dict)


def run_scan(
    scan: Scan, work: Path, chains: list[str], python: str, trees: dict | None = None
) -> Result:
    """Simulate (unless cached) and reconstruct one scan by each chain. trees: per
    instrument, a source tree whose `worker.simulate` renders its scans (default: this one)."""
    res = Result(scan)
    try:
        sim = simulate(scan, work, python, (trees or {}).get(scan.instrument))
        man = json.loads((sim / "bundle" / "manifest.json").read_text())
        res.pixel_size_um = float(man["camera"]["pixel_size_um"])
        res.size = f"{man['camera']['width']}×{man['camera']['height']}"
        res.physics = physics_summary(sim, scan)
    except (RuntimeError, OSError, ValueError, KeyError) as exc:
        # One scan the bench cannot read is reported in its row; the others still run.
        res.error = f"{type(exc).__name__}: {exc}"
        return res
    with tempfile.TemporaryDirectory(prefix="robustness-") as tmp:
        for chain in chains:
            out = Path(tmp) / chain
            status, seconds, message = reconstruct(sim / "bundle", out, chain, python)
            entry: dict = {"exit": status, "seconds": seconds}
            if status == 0:
                try:
                    entry |= figures(sim, out)
                except (OSError, ValueError, KeyError) as exc:
                    entry["message"] = f"model directory unreadable: {type(exc).__name__}: {exc}"
            else:
                entry["message"] = message
            res.chains[chain] = entry
    return res


# Table ------------------------------------------------------------------------------------

# (key, header, format, worse direction: +1 larger is worse, −1 smaller is worse)
COLUMNS = (
    ("coverage", "cov %", lambda v: f"{100 * v:.1f}", -1),
    ("mask_extra", "extra %", lambda v: f"{100 * v:.1f}", 1),
    ("height_mae_um", "MAE µm", lambda v: f"{v:.2f}", 1),
    ("height_rms_um", "RMS µm", lambda v: f"{v:.2f}", 1),
    ("height_p999_um", "p99.9 µm", lambda v: f"{v:.1f}", 1),
    ("height_max_um", "max µm", lambda v: f"{v:.0f}", 1),
    ("normal_median_deg", "n med °", lambda v: f"{v:.2f}", 1),
    ("normal_mean_deg", "n mean °", lambda v: f"{v:.2f}", 1),
    ("wedge_depth_mae_um", "wedge µm", lambda v: f"{v:.2f}", 1),
    ("fringe_spikes", "spk f", lambda v: f"{v:d}", 1),
    ("height_spikes", "spk gt", lambda v: f"{v:d}", 1),
    ("seconds", "s", lambda v: f"{v:.1f}", 1),
)
# Issue 15's "never worse" metrics, compared per scan.
COMPARED = (
    "height_mae_um",
    "height_rms_um",
    "height_p999_um",
    "height_max_um",
    "normal_median_deg",
    "normal_mean_deg",
    "wedge_depth_mae_um",
    "coverage",
)


def _fmt(entry: dict, key: str, fmt) -> str:
    v = entry.get(key)
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return fmt(v)


def scan_table(results: list[Result], chains: list[str]) -> str:
    head = "| scan | instrument | physics | chain | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * 4 + "---:|" * len(COLUMNS)]
    for r in results:
        label = f"{r.scan.name} ({r.size}, {r.pixel_size_um:.1f} µm)" if r.size else r.scan.name
        if r.error:
            lines.append(f"| {label} | {r.scan.instrument} | – | – | not simulated: {r.error} |")
            continue
        for chain in chains:
            e = r.chains[chain]
            if e["exit"] != 0:
                cells = f"exit {e['exit']}: {e.get('message', '')}"
            else:
                cells = " | ".join(_fmt(e, k, f) for k, _, f, _ in COLUMNS)
            physics = r.physics if label else ""
            lines.append(f"| {label} | {r.scan.instrument} | {physics} | {chain} | {cells} |")
            label = ""
    return "\n".join(lines)


def summary(results: list[Result], chains: list[str]) -> dict:
    """Median and worst per chain and metric; per metric, the scans where the default is
    worse than the plain chain beyond the slack."""
    done = [r for r in results if not r.error]
    out: dict = {"scans": len(done), "chains": {}}
    for chain in chains:
        ok = [r.chains[chain] for r in done if r.chains[chain]["exit"] == 0]
        stats = {"completed": len(ok), "failed": len(done) - len(ok)}
        for key, _, _, direction in COLUMNS:
            v = [e[key] for e in ok if e.get(key) is not None and math.isfinite(e[key])]
            if v:
                stats[key] = {
                    "median": float(np.median(v)),
                    "worst": float(max(v) if direction > 0 else min(v)),
                }
        out["chains"][chain] = stats
    if {"default", "plain"} <= set(chains):
        worse: dict = {}
        for key in COMPARED:
            direction = next(d for k, _, _, d in COLUMNS if k == key)
            names = []
            for r in done:
                a, b = r.chains["default"], r.chains["plain"]
                if a["exit"] != 0 and b["exit"] == 0:
                    names.append(r.scan.name)
                    continue
                va, vb = a.get(key), b.get(key)
                if a["exit"] != 0 or b["exit"] != 0 or va is None or vb is None:
                    continue
                if not (math.isfinite(va) and math.isfinite(vb)):
                    continue
                bad = va > SLACK * vb if direction > 0 else va < vb / SLACK
                if bad:
                    names.append(r.scan.name)
            worse[key] = names
        out["default_worse_than_plain"] = worse
    return out


def summary_table(summ: dict, chains: list[str]) -> str:
    head = "| chain | rows | completed | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|---|---|---:|" + "---:|" * len(COLUMNS)]
    for chain in chains:
        st = summ["chains"][chain]
        for which in ("median", "worst"):
            cells = " | ".join(
                _fmt({k: st[k][which]} if k in st else {}, k, lambda v, f=f, k=k: _num(f, k, v))
                for k, _, f, _ in COLUMNS
            )
            done = f"{st['completed']}/{summ['scans']}"
            lines.append(f"| {chain} | {which} | {done} | {cells} |")
    if "default_worse_than_plain" in summ:
        w = summ["default_worse_than_plain"]
        cells = " | ".join(str(len(w[k])) if k in w else "" for k, _, _, _ in COLUMNS)
        lines.append(f"| default worse than plain by > 10 % | scans | | {cells} |")
    return "\n".join(lines)


def _num(fmt, key, v):
    # Spike counts are medians over scans here: not integers.
    return f"{v:.0f}" if key in ("fringe_spikes", "height_spikes") else fmt(v)


def _finite(x):
    """The document with NaN and infinities as null (strict JSON)."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the 6-scan subset")
    ap.add_argument(
        "--work", type=Path, default=Path(tempfile.gettempdir()) / "dh-robustness", help="cache"
    )
    ap.add_argument("--json", type=Path, default=None, help="default WORK/robustness.json")
    ap.add_argument("--jobs", type=int, default=1, help="scans at a time")
    ap.add_argument("--chains", default="default,plain")
    ap.add_argument("--only", default="", help="comma-separated scan names")
    ap.add_argument("--instruments", default="native,mitsuba")
    ap.add_argument(
        "--mitsuba-tree",
        type=Path,
        default=None,
        help="source tree whose worker.simulate renders the Mitsuba scans (a checkout of a "
        "branch that has --renderer mitsuba; default: this tree)",
    )
    args = ap.parse_args(argv)
    python = sys.executable
    chains = [c for c in args.chains.split(",") if c]
    instruments = set(args.instruments.split(","))
    scans = [s for s in SCANS if s.quick or not args.quick]
    if args.only:
        wanted = set(args.only.split(","))
        unknown = wanted - {s.name for s in SCANS}
        if unknown:
            ap.error(f"--only: unknown scans {sorted(unknown)}; known: {[s.name for s in SCANS]}")
        scans = [s for s in SCANS if s.name in wanted]
    # Absolute: a simulator child may run in another directory (`_child`).
    args.work = args.work.resolve()
    trees = {"mitsuba": args.mitsuba_tree.resolve()} if args.mitsuba_tree else {}
    options = {i: simulator_options(python, trees.get(i)) for i in {s.instrument for s in SCANS}}
    skipped = []
    for s in list(scans):
        needs = {a for a in s.args if a.startswith("--")}
        if s.instrument not in instruments or not needs <= options[s.instrument]:
            scans.remove(s)
            skipped.append(s.name)
    if skipped:
        missing = sorted(
            {a for s in SCANS for a in s.args if a.startswith("--")}
            - set().union(*options.values())
        )
        why = f"; simulator lacks {', '.join(missing)}" if missing else ""
        print(f"skipped{why}: {', '.join(skipped)}", file=sys.stderr)
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        results = list(pool.map(lambda s: run_scan(s, args.work, chains, python, trees), scans))
    summ = summary(results, chains)
    cmd = "bench/robustness.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"## Robustness bench: `{cmd.strip()}`\n")
    print(
        f"{len(results)} scans, {time.perf_counter() - t0:.0f} s, machine: {os.cpu_count()} cores\n"
    )
    print(scan_table(results, chains))
    print("\n### Summary (median and worst over the scans)\n")
    print(summary_table(summ, chains))
    if "default_worse_than_plain" in summ:
        print("\nScans where the default is worse than the plain chain by more than 10 %:\n")
        for key, names in summ["default_worse_than_plain"].items():
            print(f"- {key}: {', '.join(names) if names else 'none'}")
    doc = {
        "command": cmd.strip(),
        "skipped": skipped,
        "scans": [
            {
                "name": r.scan.name,
                "instrument": r.scan.instrument,
                "simulate_args": list(r.scan.args),
                "physics": r.physics,
                "size": r.size,
                "pixel_size_um": r.pixel_size_um,
                "error": r.error,
                "chains": r.chains,
            }
            for r in results
        ],
        "summary": summ,
    }
    path = args.json or args.work / "robustness.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_finite(doc), indent=1, allow_nan=False))
    os.replace(tmp, path)
    print(f"\nJSON: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
