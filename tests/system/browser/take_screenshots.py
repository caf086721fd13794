"""Screenshots of the main pages for docs/screenshots/, with the browser tests' setup.

    .venv/bin/python tests/system/browser/take_screenshots.py [--out docs/screenshots]

Starts the real library service with the synthetic test tablet, plus — when the worker's
simulator and reconstruction are installed — a simulated scan reconstructed by the real
pipeline, and photographs the library, the viewer in several modes, a height profile and the
staff page with Debian's chromium (SwiftShader).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]


def _server():
    spec = importlib.util.spec_from_file_location("hammurabi_browser_server", HERE / "server.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _real_model(tmp: Path) -> Path | None:
    """Simulate and reconstruct a small tablet face with the worker, if it is there."""
    py = sys.executable
    try:
        subprocess.run(
            [
                py,
                "-m",
                "worker.simulate",
                "--out",
                str(tmp / "sim"),
                "--preset",
                "quick",
                "--seed",
                "3",
            ],
            cwd=REPO,
            check=True,
            capture_output=True,
        )
        subprocess.run(
            [
                py,
                "-m",
                "worker.reconstruct",
                str(tmp / "sim" / "bundle"),
                str(tmp / "recon"),
                "--quiet",
            ],
            cwd=REPO,
            check=True,
            capture_output=True,
        )
        # the viewer's derived maps (thumbnail, curvature, accessibility), as the worker makes
        subprocess.run(
            [
                py,
                "-c",
                "import sys; from worker.assets import derive_assets; derive_assets(sys.argv[1])",
            ]
            + [str(tmp / "recon")],
            cwd=REPO,
            check=True,
            capture_output=True,
        )
    except subprocess.CalledProcessError as exc:
        print(f"no real reconstruction ({exc.stderr.decode()[-300:]}); synthetic model only")
        return None
    return tmp / "recon"


def _wait_loaded(page, model_id) -> None:
    page.wait_for_function(
        "id => document.getElementById('viewer').dataset.loaded === id", arg=str(model_id)
    )
    page.evaluate(
        "async () => { await window.hammurabi.viewer.whenIdle();"
        " await new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r))); }"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "screenshots")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(REPO))  # run as a script: the backend is imported from the checkout
    args.out.mkdir(parents=True, exist_ok=True)
    server = _server()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        real = _real_model(tmp)
        extra = [("real", "P999003", "obverse", real)] if real else []
        lib = server.start_library(tmp / "lib", extra_models=extra)
        try:
            with sync_playwright() as p:
                browser = server.launch_chromium(p)
                page = browser.new_page(viewport={"width": 1440, "height": 900})

                page.goto(f"{lib.url}/index.html")
                page.wait_for_selector("body[data-total]")
                page.wait_for_function(
                    "n => { const imgs = [...document.querySelectorAll('.card img')];"
                    " return imgs.length >= n && imgs.every(i => i.complete && i.naturalWidth); }",
                    arg=2 if real else 1,
                )
                page.wait_for_load_state("networkidle")
                page.screenshot(path=args.out / "library.png")

                page.goto(f"{lib.url}/index.html?q=ur%20iii&period=Ur%20III")
                page.wait_for_selector(".chip[data-chip='period']")
                page.wait_for_load_state("networkidle")
                page.screenshot(path=args.out / "library-filter-chips.png")

                shown = "real" if real else "v2"
                tablet = "P999003" if real else "P999001"
                page.goto(
                    f"{lib.url}/tablet.html?id={lib.tablets[tablet]}#m={lib.models[shown]}&az=300&po=70"
                )
                _wait_loaded(page, lib.models[shown])
                page.screenshot(path=args.out / "viewer-natural.png")
                if real:
                    # The trust map of a real reconstruction (worker/trust.py, via derive_assets).
                    page.locator("#mode").select_option("trust")
                    _wait_loaded(page, lib.models[shown])
                    page.screenshot(path=args.out / "viewer-trust-real.png")
                    page.locator("#trust-layer").select_option("uncertainty")
                    _wait_loaded(page, lib.models[shown])
                    page.screenshot(path=args.out / "viewer-trust-real-uncertainty.png")

                page.goto(f"{lib.url}/tablet.html?id={lib.tablets['P999001']}#m={lib.models['v2']}")
                _wait_loaded(page, lib.models["v2"])
                for mode, file in [
                    ("relief", "viewer-relief.png"),
                    ("curvature", "viewer-curvature.png"),
                ]:
                    page.locator("#mode").select_option(mode)
                    _wait_loaded(page, lib.models["v2"])
                    page.screenshot(path=args.out / file)

                page.locator("#mode").select_option("clay")
                page.locator("#viewer").focus()
                page.keyboard.press("3")
                page.keyboard.press("h")
                for x_mm in (20.0, 28.0):
                    pt = page.evaluate(
                        "p => window.hammurabi.viewer.project(p)", [x_mm, 16.0, -1.5]
                    )
                    page.mouse.click(pt["x"], pt["y"])
                page.wait_for_selector("#profile-panel:not([hidden]) svg path.line")
                page.screenshot(path=args.out / "viewer-profile.png")

                page.goto(f"{lib.url}/staff.html")
                page.locator("#email").fill(server.STAFF_EMAIL)
                page.locator("#password").fill(server.STAFF_PASSWORD)
                page.locator("#login-form button").click()
                page.wait_for_selector("#work:not([hidden])")
                page.screenshot(path=args.out / "staff.png", full_page=True)
                browser.close()
        finally:
            lib.stop()
    print(f"screenshots in {args.out}")


if __name__ == "__main__":
    main()
