"""model.glb in a bare three.js scene, as any glTF tool would show it (SCAN_BUNDLE.md): GLTFLoader,
a default camera (looking toward −Z) framing the scene's bounding box, no knowledge of our scan
frame. The face model and the whole tablet must be upright, in view, visible and at true size.

The page's files are served by Playwright's request routing from frontend/node_modules: no
server, no network."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from worker.recon.glb import glb_bytes
from worker.register.merge import scene_glb

FRONTEND = Path(__file__).resolve().parents[3] / "frontend"
ORIGIN = "http://bare-gltf.invalid"

PAGE = f"""<!doctype html><html><body style="margin:0;background:#000">
<canvas id="c" width="320" height="240"></canvas>
<script type="importmap">{{"imports": {{
  "three": "{ORIGIN}/three/build/three.module.js",
  "three/addons/": "{ORIGIN}/three/examples/jsm/"}}}}</script>
<script type="module">
import * as THREE from 'three';
import {{ GLTFLoader }} from 'three/addons/loaders/GLTFLoader.js';
window.show = async (url) => {{
  const gltf = await new GLTFLoader().loadAsync(url);
  const scene = new THREE.Scene();
  scene.add(gltf.scene);
  scene.add(new THREE.AmbientLight(0xffffff, 1.0));
  const light = new THREE.DirectionalLight(0xffffff, 2.0);
  light.position.set(0, 0, 1);
  scene.add(light);
  const box = new THREE.Box3().setFromObject(gltf.scene);
  const size = box.getSize(new THREE.Vector3());
  const centre = box.getCenter(new THREE.Vector3());
  const camera = new THREE.PerspectiveCamera(40, 320 / 240, 1e-4, 100);
  // The default glTF camera looks toward -Z; back it off along +Z until the box fits.
  const fit = Math.max(size.x / camera.aspect, size.y) / 2 / Math.tan(THREE.MathUtils.degToRad(20));
  camera.position.set(centre.x, centre.y, box.max.z + 1.2 * fit);
  camera.near = fit / 100; camera.far = 10 * fit + size.z; camera.updateProjectionMatrix();
  const renderer = new THREE.WebGLRenderer({{ canvas: document.getElementById('c'),
    preserveDrawingBuffer: true }});
  renderer.setClearColor(0x000000, 1);
  renderer.render(scene, camera);
  const gl = renderer.getContext();
  const px = new Uint8Array(320 * 240 * 4);
  gl.readPixels(0, 0, 320, 240, gl.RGBA, gl.UNSIGNED_BYTE, px);
  return {{ size: [size.x, size.y, size.z], pixels: Array.from(px) }};
}};
window.ready = true;
</script></body></html>"""


def _route(page, files: dict[str, bytes]):
    def handle(route):
        path = route.request.url[len(ORIGIN) :]
        if path in files:
            body = files[path]
            ctype = "model/gltf-binary" if path.endswith(".glb") else "text/html"
        elif path.startswith("/three/"):
            target = (FRONTEND / "node_modules" / path.lstrip("/")).resolve()
            if not target.is_file() or FRONTEND not in target.parents:
                return route.fulfill(status=404, body="")
            body, ctype = target.read_bytes(), "text/javascript"
        else:
            return route.fulfill(status=404, body="")
        route.fulfill(status=200, body=body, headers={"Content-Type": ctype})

    page.route(f"{ORIGIN}/**", handle)


def _image(result) -> np.ndarray:
    # readPixels starts at the bottom row: flip so that row 0 is the top of the screen.
    return np.asarray(result["pixels"], np.uint8).reshape(240, 320, 4)[::-1, :, :3]


def _face_model() -> bytes:
    rows, cols, s_um = 60, 80, 100.0
    y, x = np.mgrid[0:rows, 0:cols]
    r2 = ((x - cols / 2) / cols) ** 2 + ((y - rows / 2) / rows) ** 2
    h = (800.0 * (1 - 4 * r2)).astype(np.float32)
    n = np.zeros((rows, cols, 3), np.float32)
    n[..., 2] = -1
    albedo = np.full((rows, cols, 3), (40, 40, 200), np.uint8)  # blue
    albedo[: rows // 3] = (40, 200, 40)  # the image's top third green
    data, _ = glb_bytes(h, np.ones((rows, cols), bool), n, albedo, pixel_size_um=s_um)
    return data


def _coloured_box(lo, hi, rgb) -> trimesh.Trimesh:
    box = trimesh.creation.box(bounds=np.array([lo, hi], float))
    box.visual.vertex_colors = np.tile([*rgb, 255], (len(box.vertices), 1)).astype(np.uint8)
    return box


def _whole_tablet() -> bytes:
    # Scan-frame mm (y down, z away from the camera): the obverse in front, green on top.
    obverse = trimesh.util.concatenate(
        [
            _coloured_box((0, 0, 0), (40, 10, 20), (40, 200, 40)),
            _coloured_box((0, 10, 0), (40, 30, 20), (40, 40, 200)),
        ]
    )
    reverse = _coloured_box((0, 0, 1), (40, 30, 21), (200, 40, 40))  # hidden behind: red
    return scene_glb(
        {"obverse": obverse, "reverse": reverse}, {"obverse": np.eye(4), "reverse": np.eye(4)}
    )


@pytest.mark.parametrize(
    ("name", "make", "size_m"),
    [
        ("face", _face_model, (79 * 100e-6, 59 * 100e-6, None)),
        ("tablet", _whole_tablet, (0.040, 0.030, 0.021)),
    ],
)
def test_generic_threejs_scene_shows_model_upright_in_view_at_true_size(
    page, name, make, size_m, tmp_path
):
    _route(page, {"/index.html": PAGE.encode(), f"/{name}.glb": make()})
    page.goto(f"{ORIGIN}/index.html")
    page.wait_for_function("window.ready === true")
    result = page.evaluate(f"window.show('{ORIGIN}/{name}.glb')")
    for got, want in zip(result["size"], size_m, strict=True):
        if want is not None:
            assert got == pytest.approx(want, rel=1e-3), result["size"]
    img = _image(result)
    lit = img.max(axis=2) > 30
    assert lit.mean() > 0.2, "the model is not in view (or faces away from the camera)"
    rows = np.flatnonzero(lit.any(axis=1))
    top = img[rows[0] : rows[0] + max(2, len(rows) // 6)]
    bottom = img[rows[-1] - max(2, len(rows) // 6) : rows[-1] + 1]

    def mean(a, channel):
        return a[..., channel].astype(float).mean()

    # Upright: the green top of the image is at the top of the screen, the blue below.
    assert mean(top, 1) > mean(top, 2) and mean(bottom, 2) > mean(bottom, 1)
    # The side that faced the scanner faces the default camera: no red (the reverse) shows.
    assert (img[..., 0].astype(int) - img[..., 1] > 60).mean() < 0.01
