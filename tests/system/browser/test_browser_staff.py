"""Staff pages in a real browser: log in, create a tablet, resumable upload, follow the job."""

from __future__ import annotations

import httpx
import numpy as np


def _small_bundle(tmp_path):
    """A valid photometric-only bundle (SCAN_BUNDLE.md) of a few tens of kB, as a ZIP."""
    from worker.bundle import write_bundle

    rng = np.random.default_rng(11)
    frames = [{"file": "dark.png", "kind": "dark"}] + [
        {"file": f"p{az:03d}.png", "kind": "photometric", "azimuth_deg": az}
        for az in (0, 90, 180, 270)
    ]
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {"id": f"browser-test-{rng.integers(1 << 30)}", "face": "obverse"},
        "camera": {"width": 64, "height": 48, "pixel_size_um": 50.0, "bit_depth": 12},
        "source": {"polar_deg": 45},
        "frames": frames,
    }
    images = {f["file"]: rng.integers(0, 4096, size=(48, 64), dtype=np.uint16) for f in frames}
    return write_bundle(tmp_path / "bundle.zip", manifest, images, as_zip=True)


def test_login_create_tablet_resume_an_upload_and_read_why_the_job_failed(page, library, tmp_path):
    server = __import__("sys").modules["hammurabi_browser_server"]
    bundle = _small_bundle(tmp_path)
    size = bundle.stat().st_size
    chunk = server.UPLOAD_CHUNK_BYTES
    assert size > 3 * chunk  # several chunks, so that resuming means something

    page.goto(f"{library.url}/staff.html")
    page.locator("#password").fill("wrong password")
    page.locator("#email").fill(server.STAFF_EMAIL)
    page.locator("#login-form button").click()
    page.wait_for_selector("#login-error:not([hidden])")
    page.locator("#password").fill(server.STAFF_PASSWORD)
    page.locator("#login-form button").click()
    page.wait_for_selector("#work:not([hidden])")

    form = page.locator("#tablet-form")
    form.locator("[name=designation]").fill("BM 12345")
    form.locator("[name=period]").fill("Neo-Assyrian")
    form.locator("button[type=submit]").click()
    page.wait_for_selector("#tablet-result a")
    tablet_id = int(page.locator("#upload-tablet").input_value())

    # An earlier attempt (another tab, before a reload) sent the first chunk and was cut off:
    # it left its upload id in localStorage, as the page does.
    with httpx.Client(base_url=library.url) as client:
        r = client.post(
            "/api/v1/auth/login",
            json={"email": server.STAFF_EMAIL, "password": server.STAFF_PASSWORD},
        )
        r.raise_for_status()
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

    # No broker listens in this setup: the library fails the job and the page says why.
    page.wait_for_function(
        "document.getElementById('job-state').dataset.state === 'failed'", timeout=30000
    )
    assert "job queue" in page.locator("#job-error").inner_text()
    assert page.locator("#job-retry").is_visible()
    assert page.evaluate("localStorage.length") == 0  # the finished upload is forgotten

    with httpx.Client(base_url=library.url) as client:
        scans = client.get(f"/api/v1/tablets/{tablet_id}/scans").json()
    # the scan exists (public tablet: readable anonymously) with every byte of the bundle
    assert len(scans) == 1 and scans[0]["size_bytes"] == size
