"""View-dependent streaming in the browser (issue 19): a real library server on loopback, a
tiled model, Debian's Chromium (SwiftShader, 1280 × 800) driven by Playwright.

    .venv/bin/python bench/streaming.py --model face100=PATH [--model tablet13=PATH ...]
        [--budget-mb 256] [--error-px 1] [--orbit-frames 60]

PATH is a model directory with tiles/ (tiles/index.json written by the worker's tile
builder); a model directory without tiles is measured on today's single-mesh path for
comparison (first render: the model drawn; orbiting; bytes of its assets). For each model the script opens the tablet page and measures:

- first render: from navigation to the first frame that drew a tile (the root: a coarse model);
- a typical session: the overview, then three wheel zooms (x4 and x4 again under one cursor
  position, then back to the overview and x16 under another), each timed from the wheel
  event to the frame where the tile under the cursor is at full detail (a leaf, or a
  screen-space error within the target: the renderer wants nothing finer there) and nothing
  is left loading
  (and, separately, to the first frame where that tile alone is at full detail, while other
  tiles may still load: what the tiles-under-the-cursor-first order shortens);
- bytes transferred (Resource Timing transferSize of the tile requests) as a fraction of the
  whole tileset (every level) and of its finest level alone;
- GPU memory: the tile cache's own accounting (3d-tiles-renderer's LRU bytes: geometry and
  every texture of the loaded tiles), its peak over the session against the budget;
- frames per second while orbiting at the overview (the view turned 2 degrees a frame).

Goals (issue 19): first render <= 1 s, full detail under the cursor <= 2 s after a zoom,
<= 20 % of the full data for the session, GPU memory under the budget, >= 30 fps orbiting.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VIEWPORT = {"width": 1280, "height": 800}

# Polled each animation frame from page start: when did the first tile reach the screen?
FIRST_RENDER_PROBE = """
(() => {
  const poll = () => {
    const s = window.hammurabi?.viewer?.streaming?.();
    if (s && s.visibleTiles > 0) { window.__firstTileMs = performance.now(); return; }
    requestAnimationFrame(poll);
  };
  requestAnimationFrame(poll);
  window.addEventListener('wheel', () => { window.__wheelMs = performance.now(); },
    { capture: true });
})();
"""

# After a zoom: frames until the tile under (x, y) is sufficient and nothing is loading; also
# when the tile under (x, y) was first sufficient (the cursor's detail, other tiles may load).
WAIT_DETAIL = """
async ([x, y]) => {
  const v = window.hammurabi.viewer;
  const frame = () => new Promise(r => requestAnimationFrame(r));
  const deadline = performance.now() + 120000;
  let peak = 0;
  let cursorMs = null;
  for (;;) {
    v.invalidate();
    await frame();
    const s = v.streaming();
    peak = Math.max(peak, s.bytesUsed);
    const hit = v.pick(x, y);
    const tile = hit && v.model.tiles.describeTile(hit.object);
    if (tile && tile.sufficient && cursorMs === null) cursorMs = performance.now() - window.__wheelMs;
    if (tile && tile.sufficient && s.idle) {
      return { ms: performance.now() - window.__wheelMs, cursorMs, tile: { ...tile }, peak, stats: s };
    }
    if (performance.now() > deadline) {
      return { ms: null, cursorMs, tile: tile && { ...tile }, peak, stats: s };
    }
  }
}
"""

ORBIT = """
async (n) => {
  const v = window.hammurabi.viewer;
  const frame = () => new Promise(r => requestAnimationFrame(r));
  await frame();
  const t0 = performance.now();
  for (let i = 0; i < n; i++) { v.orbitBy(2); await frame(); }
  const seconds = (performance.now() - t0) / 1000;
  return { fps: n / seconds, stats: v.streaming() };
}
"""

# Where the first render's time went: when each step's request ended (Resource Timing, ms from
# navigation), the viewer's own marks (tiles.js loaded, root tileset, first tile parsed) and
# the first frame with a tile. Steps not seen are null (e.g. marks of an older build).
FIRST_RENDER_STEPS = """
() => {
  const r = performance.getEntriesByType('resource');
  const nav = performance.getEntriesByType('navigation')[0];
  const first = (re, key = 'responseEnd') => {
    const hits = r.filter(e => re.test(e.name)).map(e => e[key]);
    return hits.length ? Math.min(...hits) : null;
  };
  const mark = (name) => performance.getEntriesByName(name)[0]?.startTime ?? null;
  return {
    html: nav.responseEnd,
    bundle: first(/\\/assets\\/tablet-[^/]*\\.js$/),
    dom_ready: nav.domContentLoadedEventEnd,
    model_api: first(/\\/models\\/\\d+$/),
    tiles_js: first(/\\/assets\\/tiles-[^/]*\\.js$/),
    index_json: first(/tiles\\/index\\.json$/),
    root_tileset: first(/tileset\\.json$/),
    tileset_ready: mark('dh:tileset-ready'),
    glb_request: first(/\\.glb$/, 'startTime'),
    glb_received: first(/\\.glb$/),
    tile_parsed: mark('dh:tile-parsed'),
    first_frame: window.__firstTileMs,
    first_frame_render_ms: window.hammurabi?.viewer?.frameStats?.().firstTileRenderMs ?? null,
  };
}
"""

TRANSFERRED = """
() => performance.getEntriesByType('resource')
  .filter(e => e.name.includes('/assets/tiles/'))
  .reduce((n, e) => n + e.transferSize, 0)
"""


def _server_module():
    path = REPO / "tests" / "system" / "browser" / "server.py"
    spec = importlib.util.spec_from_file_location("hammurabi_browser_server", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _tileset_bytes(model_dir: Path) -> tuple[int, int]:
    """(bytes of every tile content, bytes of the finest level's) under tiles/."""
    import json

    total = sum(p.stat().st_size for p in (model_dir / "tiles").rglob("*.glb"))
    finest = 0
    for tileset in (model_dir / "tiles").rglob("tileset.json"):
        root = json.loads(tileset.read_text())["root"]
        stack = [root]
        while stack:
            t = stack.pop()
            kids = t.get("children") or []
            stack.extend(kids)
            uri = (t.get("content") or {}).get("uri", "")
            if not kids and uri.endswith(".glb"):
                finest += (tileset.parent / uri).stat().st_size
    return total, finest


def wheel_zoom(page, x: float, y: float, factor: float) -> None:
    """One wheel event zooming by ``factor`` about (x, y) (OrbitControls: 0.95 per 100 of
    deltaY, three.js r187)."""
    import math

    page.mouse.move(x, y)
    page.mouse.wheel(0, -100 * math.log(factor) / -math.log(0.95))


def measure(page, lib, label: str, model_dir: Path, args) -> dict:
    tablet_id = lib.tablets["P999003"]
    page.add_init_script(FIRST_RENDER_PROBE)
    page.goto(
        f"{lib.url}/tablet.html?id={tablet_id}&tile_budget_mb={args.budget_mb}"
        f"&tile_error_px={args.error_px}#m={lib.models[label]}"
    )
    if not (model_dir / "tiles" / "index.json").is_file():
        return measure_single_mesh(page, label, model_dir, args)
    page.wait_for_function("() => window.__firstTileMs !== undefined", timeout=120000)
    first_ms = page.evaluate("() => window.__firstTileMs")
    steps = page.evaluate(FIRST_RENDER_STEPS)
    box = page.locator("#viewer").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    a = (box["x"] + box["width"] * 0.4, box["y"] + box["height"] * 0.45)
    b = (box["x"] + box["width"] * 0.65, box["y"] + box["height"] * 0.6)
    overview = page.evaluate(WAIT_DETAIL, [cx, cy])
    orbit = page.evaluate(ORBIT, args.orbit_frames)
    page.evaluate("() => window.hammurabi.viewer.resetView()")
    page.evaluate(WAIT_DETAIL, [cx, cy])
    zooms = []
    for pos, factor, reset in ((a, 4, False), (a, 4, False), (b, 16, True)):
        if reset:
            page.evaluate("() => window.hammurabi.viewer.resetView()")
            page.evaluate(WAIT_DETAIL, [cx, cy])
        wheel_zoom(page, *pos, factor)
        zooms.append(page.evaluate(WAIT_DETAIL, list(pos)))
    transferred = page.evaluate(TRANSFERRED)
    total, finest = _tileset_bytes(model_dir)
    peak = max([overview["peak"], *[z["peak"] for z in zooms], orbit["stats"]["bytesUsed"]])
    import json

    index = json.loads((model_dir / "tiles" / "index.json").read_text())
    faces = [  # a whole tablet: its faces' own index.json files
        json.loads((model_dir / "tiles" / p).read_text()) for p in index.get("faces", {}).values()
    ] or [index]
    return {
        "label": label,
        "mpx": sum(f["width_px"] * f["height_px"] for f in faces) / 1e6,
        "first_ms": first_ms,
        "first_steps": steps,
        "zoom_ms": [z["ms"] for z in zooms],
        "cursor_ms": [z["cursorMs"] for z in zooms],
        "zoom_steps": [z["tile"] and z["tile"].get("pixel_step") for z in zooms],
        "transferred": transferred,
        "total": total,
        "finest": finest,
        "peak": peak,
        "budget": zooms[-1]["stats"]["budgetBytes"],
        "fps": orbit["fps"],
    }


def measure_single_mesh(page, label: str, model_dir: Path, args) -> dict:
    """The same page with a model without tiles (today's path: model.glb and full-size
    textures), for comparison: first render (the model drawn) and orbiting."""
    page.wait_for_function("() => document.getElementById('viewer').dataset.loaded")
    first_ms = page.evaluate("() => performance.now()")
    orbit = page.evaluate(ORBIT.replace("stats: v.streaming()", "stats: null"), args.orbit_frames)
    total = sum(p.stat().st_size for p in model_dir.rglob("*") if p.is_file())
    transferred = page.evaluate(
        """() => performance.getEntriesByType('resource')
          .filter(e => e.name.includes('/assets/')).reduce((n, e) => n + e.transferSize, 0)"""
    )
    return {
        "label": f"{label} (no tiles)",
        "mpx": float("nan"),
        "first_ms": first_ms,
        "zoom_ms": [],
        "cursor_ms": [],
        "zoom_steps": [],
        "transferred": transferred,
        "total": total,
        "finest": total,
        "peak": float("nan"),
        "budget": float("nan"),
        "fps": orbit["fps"],
    }


@contextlib.contextmanager
def library_and_browser(models: list[tuple[str, Path]], dist: Path | None = None):
    """A library server on loopback holding `models` ((label, model directory), each an
    obverse of P999003) and Debian's Chromium: yields (library, browser); both stopped after.
    `dist`: a saved frontend build to serve instead of building this tree's."""
    server = _server_module()
    if dist is not None:
        server.ensure_frontend_built = lambda: dist.resolve()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="bench-streaming-") as tmp:
        lib = server.start_library(
            Path(tmp), extra_models=[(lb, "P999003", "obverse", d) for lb, d in models]
        )
        try:
            with sync_playwright() as p:
                browser = server.launch_chromium(p)
                try:
                    yield lib, browser
                finally:
                    browser.close()
        finally:
            lib.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model", action="append", required=True, help="LABEL=PATH of a model dir with tiles/"
    )
    parser.add_argument("--budget-mb", type=float, default=256)
    parser.add_argument("--error-px", type=float, default=1)
    parser.add_argument("--orbit-frames", type=int, default=60)
    parser.add_argument(
        "--dist",
        type=Path,
        help="serve this built frontend (e.g. a copy of an earlier build, for before/after) "
        "instead of building frontend/dist",
    )
    args = parser.parse_args()
    models = []
    for spec in args.model:
        label, _, path = spec.partition("=")
        model_dir = Path(path)
        if not (model_dir / "model.glb").is_file() and not (model_dir / "tiles").is_dir():
            parser.error(f"{path}: not a model directory (no model.glb, no tiles/)")
        if label in {lb for lb, _ in models}:
            parser.error(f"{label}: each --model needs its own label")
        models.append((label, model_dir))

    if args.dist is not None and not (args.dist / "tablet.html").is_file():
        parser.error(f"{args.dist}: not a built frontend (no tablet.html)")
    rows = []
    with library_and_browser(models, args.dist) as (lib, browser):
        for label, model_dir in models:
            context = browser.new_context(viewport=VIEWPORT)
            page = context.new_page()
            start = time.perf_counter()
            rows.append(measure(page, lib, label, model_dir, args))
            rows[-1]["wall_s"] = time.perf_counter() - start
            print(f"measured {label}: {rows[-1]}", file=sys.stderr, flush=True)
            context.close()

    mb = 1024 * 1024
    load = os.getloadavg()[0]
    print(
        f"budget {args.budget_mb:g} MB, error target {args.error_px:g} px, "
        f"Chromium/SwiftShader {VIEWPORT['width']}x{VIEWPORT['height']}, "
        f"{os.cpu_count()} CPUs, load average {load:.1f} at the end"
    )
    head = (
        "| model | Mpx | first render ms | full detail after zoom 1/2/3 ms (pixel step) "
        "| cursor's tile at full detail ms | transferred MB | % of tileset | % of finest level | GPU peak MB / budget | "
        "orbit fps |"
    )
    print(head)
    print("|---" * (head.count("|") - 1) + "|")
    for r in rows:
        zooms = " / ".join(
            f"{ms:.0f} ({step})" if ms is not None else "timeout"
            for ms, step in zip(r["zoom_ms"], r["zoom_steps"], strict=True)
        )
        cursor = " / ".join(f"{ms:.0f}" if ms is not None else "timeout" for ms in r["cursor_ms"])
        print(
            f"| {r['label']} | {r['mpx']:.1f} | {r['first_ms']:.0f} | {zooms} | {cursor} "
            f"| {r['transferred'] / mb:.1f} | {100 * r['transferred'] / r['total']:.1f} "
            f"| {100 * r['transferred'] / max(r['finest'], 1):.1f} "
            f"| {r['peak'] / mb:.0f} / {r['budget'] / mb:.0f} | {r['fps']:.1f} |"
        )
    print("\nFirst render, ms from navigation (request ends; viewer marks):")
    for r in rows:
        steps = r.get("first_steps") or {}
        cells = ", ".join(
            f"{k} {v:.0f}" for k, v in steps.items() if isinstance(v, int | float) and v == v
        )
        print(f"- {r['label']}: {cells}")


if __name__ == "__main__":
    main()
