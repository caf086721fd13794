"""Where a streamed frame's time goes (issue 19): orbit frames and a wheel zoom, profiled.

    .venv/bin/python bench/streaming_profile.py --model LABEL=MODEL_DIR [--model ...]
        [--frames 20] [--dist SAVED_BUILD] [--trace-dir DIR]

The page and server are bench/streaming.py's (Chromium + SwiftShader at 1280 x 800). For each
model, after the overview has settled: `--frames` orbit steps (2 degrees each, adaptive
resolution on), then one x4 wheel zoom at the viewer's centre followed frame by frame until the
tile under the cursor is at full detail and nothing loads. Two views of the same frames:

- the page's own (viewer frameStats, one record per frame): the interval between frames, the
  tiles' update and the render call on the page's thread (WebGL commands issued, not drawn),
  draw calls, the pixel ratio's scale;
- Chromium's trace (Playwright's `browser.start_tracing`, Chrome trace event format): the busy
  time of each process thread over the same window (top-level events only, so nested events
  are not counted twice), and the GPU thread's largest event names: what the GPU process did
  with those commands (SwiftShader rasterises on the CPU) and the compositor's share.

Prints a table per model and phase; `--trace-dir` keeps the raw traces (open them in
chrome://tracing or Perfetto).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import streaming  # noqa: E402  (bench/streaming.py: the server, page probes, wheel zoom)

CATEGORIES = [
    "toplevel",
    "gpu",
    "cc",
    "viz",
    "blink",
    "v8",
    "disabled-by-default-devtools.timeline",
]

ORBIT_FRAMES = """
async (n) => {
  const v = window.hammurabi.viewer;
  const frame = () => new Promise(r => requestAnimationFrame(r));
  await frame();
  const out = [];
  let last = performance.now();
  for (let i = 0; i < n; i++) {
    v.orbitBy(2);
    await frame();
    const now = performance.now();
    out.push({ intervalMs: now - last, ...v.frameStats() });
    last = now;
  }
  return out;
}
"""

ZOOM_FRAMES = """
async ([x, y]) => {
  const v = window.hammurabi.viewer;
  const frame = () => new Promise(r => requestAnimationFrame(r));
  const deadline = performance.now() + 120000;
  const out = [];
  let last = window.__wheelMs;
  for (;;) {
    v.invalidate();
    await frame();
    const now = performance.now();
    const s = v.streaming();
    const hit = v.pick(x, y);
    const tile = hit && v.model.tiles.describeTile(hit.object);
    out.push({ intervalMs: now - last, ...v.frameStats(), loading: !s.idle, sufficient: Boolean(tile?.sufficient) });
    last = now;
    if ((tile && tile.sufficient && s.idle) || now > deadline) return { ms: now - window.__wheelMs, frames: out };
  }
}
"""


def thread_busy_ms(trace: dict) -> tuple[dict[str, float], dict[str, float], float]:
    """(busy ms per "process/thread" name, ms per event name on the GPU main thread, window ms)
    from a Chrome trace: top-level complete events ("X") only, so nested events are not
    counted twice."""
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    names = {}
    procs = {}
    for e in events:
        if e.get("ph") == "M" and e.get("name") == "thread_name":
            names[(e["pid"], e["tid"])] = e["args"]["name"]
        if e.get("ph") == "M" and e.get("name") == "process_name":
            procs[e["pid"]] = e["args"]["name"]
    by_thread = defaultdict(list)
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            by_thread[(e["pid"], e["tid"])].append(e)
    busy: dict[str, float] = defaultdict(float)
    gpu_events: dict[str, float] = defaultdict(float)
    t_min, t_max = float("inf"), float("-inf")
    for key, evs in by_thread.items():
        evs.sort(key=lambda e: (e["ts"], -e["dur"]))
        label = f"{procs.get(key[0], key[0])}/{names.get(key, key[1])}"
        end = float("-inf")
        for e in evs:
            if e["ts"] < end:
                continue  # nested in (or overlapping) the previous top-level event
            end = e["ts"] + e["dur"]
            busy[label] += e["dur"] / 1000
            t_min, t_max = min(t_min, e["ts"]), max(t_max, end)
            if names.get(key) == "CrGpuMain":
                gpu_events[e["name"]] += e["dur"] / 1000
    return dict(busy), dict(gpu_events), (t_max - t_min) / 1000 if t_max > t_min else 0.0


def summarise(label: str, phase: str, frames: list[dict], trace: dict, wall_ms: float) -> None:
    n = len(frames)
    # an older build (--dist) has only some of frameStats' fields: nan for the others
    mean = lambda k: sum(f.get(k, float("nan")) for f in frames) / max(n, 1)  # noqa: E731
    print(f"\n### {label}, {phase}: {n} frames, {wall_ms:.0f} ms")
    print(
        f"page thread per frame: interval {mean('intervalMs'):.1f} ms, tiles' update "
        f"{mean('updateMs'):.2f} ms, render call {mean('renderMs'):.2f} ms, "
        f"draw calls {mean('drawCalls'):.1f}, triangles {mean('triangles'):.0f}, "
        f"scale {mean('lastScale'):.2f}"
    )
    busy, gpu, window = thread_busy_ms(trace)
    print(f"trace window {window:.0f} ms; busy ms per thread (top 8), per frame:")
    for name, ms in sorted(busy.items(), key=lambda kv: -kv[1])[:8]:
        print(f"- {name}: {ms:.0f} ms ({ms / max(n, 1):.1f} per frame)")
    print("GPU main thread's events (top 6):")
    for name, ms in sorted(gpu.items(), key=lambda kv: -kv[1])[:6]:
        print(f"- {name}: {ms:.0f} ms")


nan = float("nan")


def profile(browser, page, lib, label: str, args) -> None:
    tablet_id = lib.tablets["P999003"]
    page.add_init_script(streaming.FIRST_RENDER_PROBE)
    page.goto(f"{lib.url}/tablet.html?id={tablet_id}#m={lib.models[label]}")
    page.wait_for_function("() => window.__firstTileMs !== undefined", timeout=120000)
    box = page.locator("#viewer").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.evaluate(streaming.WAIT_DETAIL, [cx, cy])
    for phase in ("orbit", "zoom x4"):
        browser.start_tracing(page=page, categories=CATEGORIES)
        if phase == "orbit":
            frames = page.evaluate(ORBIT_FRAMES, args.frames)
            wall = sum(f["intervalMs"] for f in frames)
        else:
            page.evaluate("() => window.hammurabi.viewer.resetView()")
            page.evaluate(streaming.WAIT_DETAIL, [cx, cy])
            streaming.wheel_zoom(page, cx, cy, 4)
            out = page.evaluate(ZOOM_FRAMES, [cx, cy])
            frames, wall = out["frames"], out["ms"]
        raw = browser.stop_tracing()
        trace = json.loads(raw)
        if args.trace_dir:
            args.trace_dir.mkdir(parents=True, exist_ok=True)
            (args.trace_dir / f"{label}-{phase.split()[0]}.json").write_bytes(raw)
        summarise(label, phase, frames, trace, wall)
        if phase != "orbit":
            print("per frame (interval, update, render ms, calls, loading):")
            for f in frames:
                print(
                    f"  {f['intervalMs']:.0f} {f.get('updateMs', nan):.1f} {f.get('renderMs', nan):.1f} "
                    f"{f.get('drawCalls', '?')} {'L' if f['loading'] else '-'}"
                    f"{' S' if f['sufficient'] else ''}"
                )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", required=True, help="LABEL=MODEL_DIR")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--dist", type=Path, help="serve this built frontend instead")
    parser.add_argument("--trace-dir", type=Path, help="keep the raw traces here")
    args = parser.parse_args()
    models = [(lb, Path(p)) for lb, _, p in (m.partition("=") for m in args.model)]
    for label, d in models:
        if not (d / "tiles" / "index.json").is_file():
            parser.error(f"{label}: {d} has no tiles/index.json")
    print(f"load average {os.getloadavg()[0]:.1f} at the start")
    with streaming.library_and_browser(models, args.dist) as (lib, browser):
        for label, _ in models:
            context = browser.new_context(viewport=streaming.VIEWPORT)
            profile(browser, context.new_page(), lib, label, args)
            context.close()
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
