"""Staff pages in a real browser, end to end: log in, create a tablet, upload a bundle with a
resumed upload, follow the job on a real reconstruction worker until the model is shown in the
viewer — or read why the job failed."""

from __future__ import annotations

import subprocess
import sys

import httpx
import numpy as np
import pytest


@pytest.fixture(scope="module")
def worker(library, server_module, tmp_path_factory):
    """A real ``hammurabi worker`` on the library's embedded broker, for this module."""
    process = server_module.start_worker(library, tmp_path_factory.mktemp("worker") / "log")
    yield process
    server_module.stop_worker(process)


@pytest.fixture(scope="module")
def simulated_bundle(tmp_path_factory, server_module):
    """A small simulated obverse scan (worker.simulate, quick preset, 96 × 64 px) as a ZIP."""
    out = tmp_path_factory.mktemp("sim")
    subprocess.run(
        [sys.executable, "-m", "worker.simulate", "--out", str(out), "--preset", "quick"]
        + ["--seed", "4", "--size", "96x64", "--zip"],
        cwd=server_module.REPO,
        check=True,
        capture_output=True,
    )
    return out / "bundle.zip"


def _unusable_bundle(tmp_path):
    """A valid bundle (SCAN_BUNDLE.md) that cannot be reconstructed: one light, no fringes."""
    from worker.bundle import write_bundle

    rng = np.random.default_rng(11)
    frames = [
        {"file": "dark.png", "kind": "dark"},
        {"file": "p000.png", "kind": "photometric", "azimuth_deg": 0},
    ]
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {"id": f"browser-test-{rng.integers(1 << 30)}", "face": "reverse"},
        "camera": {"width": 64, "height": 48, "pixel_size_um": 50.0, "bit_depth": 12},
        "source": {"polar_deg": 45},
        "frames": frames,
    }
    images = {f["file"]: rng.integers(0, 4096, size=(48, 64), dtype=np.uint16) for f in frames}
    return write_bundle(tmp_path / "one-light.zip", manifest, images, as_zip=True)


def _log_in(page, library, server):
    page.goto(f"{library.url}/staff.html")
    page.locator("#email").fill(server.STAFF_EMAIL)
    page.locator("#password").fill("wrong password")
    page.locator("#login-form button").click()
    page.wait_for_selector("#login-error:not([hidden])")
    page.locator("#password").fill(server.STAFF_PASSWORD)
    page.locator("#login-form button").click()
    page.wait_for_selector("#work:not([hidden])")


def _create_tablet(page, designation: str) -> int:
    form = page.locator("#tablet-form")
    form.locator("[name=designation]").fill(designation)
    form.locator("[name=period]").fill("Neo-Assyrian")
    form.locator("button[type=submit]").click()
    page.wait_for_selector("#tablet-result a")
    return int(page.locator("#upload-tablet").input_value())


def test_upload_resumes_and_ends_in_a_model_shown_in_the_viewer(
    page, library, server_module, worker, simulated_bundle
):
    server = server_module
    bundle = simulated_bundle
    size = bundle.stat().st_size
    chunk = server.UPLOAD_CHUNK_BYTES
    assert size > 3 * chunk  # several chunks, so that resuming means something

    _log_in(page, library, server)
    tablet_id = _create_tablet(page, "BM 12345")

    # An earlier attempt (before a reload) sent the first chunk and was cut off; it left its
    # upload id in localStorage, as the page does.
    with httpx.Client(base_url=library.url) as client:
        client.post(
            "/api/v1/auth/login",
            json={"email": server.STAFF_EMAIL, "password": server.STAFF_PASSWORD},
        ).raise_for_status()
        up = client.post(
            "/api/v1/uploads",
            json={"tablet_id": tablet_id, "filename": bundle.name, "size_bytes": size},
        ).json()
        client.put(
            f"/api/v1/uploads/{up['id']}/chunks",
            params={"offset": 0},
            content=bundle.read_bytes()[:chunk],
        ).raise_for_status()
    page.locator("#upload-file").set_input_files(str(bundle))
    page.evaluate(
        """([tabletId, id]) => {
        const f = document.getElementById('upload-file').files[0];
        localStorage.setItem(`hammurabi.upload:${tabletId}:${f.name}:${f.size}:${f.lastModified}`, id);
      }""",
        [tablet_id, up["id"]],
    )
    page.locator("#upload-start").click()
    page.wait_for_selector("#job-section:not([hidden])")
    assert page.locator("#upload-progress").get_attribute("data-resumed-from") == str(chunk)
    assert page.evaluate("localStorage.length") == 0  # the finished upload is forgotten

    # the real worker reconstructs it; the page follows the job until the model is there
    page.wait_for_selector("#job-done:not([hidden])", timeout=180000)  # worker boot + job, busy CI
    assert page.locator("#job-state").inner_text() == "succeeded"
    page.locator("#job-link").click()
    page.wait_for_function("() => document.getElementById('viewer').dataset.loaded", timeout=30000)
    page.evaluate("() => window.hammurabi.viewer.whenIdle()")
    png = page.locator("#viewer").screenshot()
    import io

    from PIL import Image

    px = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float) / 255
    background = np.array([0x1D, 0x1F, 0x24]) / 255
    assert (np.abs(px - background).sum(axis=-1) > 0.05).mean() > 0.2  # the model is drawn
    assert "obverse" in page.locator("#model-select").inner_text()


def test_a_job_that_fails_says_why(page, library, server_module, worker, tmp_path):
    _log_in(page, library, server_module)
    _create_tablet(page, "BM 54321")
    page.locator("#upload-file").set_input_files(str(_unusable_bundle(tmp_path)))
    page.locator("#upload-start").click()
    page.wait_for_selector("#job-section:not([hidden])")
    page.wait_for_function(
        "() => document.getElementById('job-state').dataset.state === 'failed'", timeout=180000
    )
    reason = page.locator("#job-error").inner_text()
    assert reason.startswith("The reconstruction failed: ") and len(reason) > 40, reason
    assert page.locator("#job-retry").is_visible()
