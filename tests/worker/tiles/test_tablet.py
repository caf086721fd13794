"""Tiles of a whole tablet: each face's tileset under tiles/faces/<label>/, a root tileset
referencing them (external tilesets) with each face's transform into the tablet frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from worker.simulate.large_face import write_large_face
from worker.tiles import TileError
from worker.tiles.tablet import build_tablet_tiles, transformed_box


@pytest.fixture(scope="module")
def tablet(tmp_path_factory):
    root = tmp_path_factory.mktemp("tablet")
    obverse, reverse = root / "obverse", root / "reverse"
    write_large_face(obverse, width_px=600, height_px=520, seed=4)
    write_large_face(reverse, width_px=560, height_px=500, seed=5)
    flip = np.eye(4)  # the reverse: turned over about the tablet's long (y) axis, 20 mm back
    flip[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    flip[:3, 3] = [15.0, 0.0, 20.0]
    out = root / "whole"
    out.mkdir()
    faces = {"faces/obverse": (obverse, np.eye(4)), "faces/reverse": (reverse, flip)}
    index = build_tablet_tiles(out, faces)
    return out, faces, index


def test_root_tileset_references_every_face_with_its_transform(tablet):
    out, faces, index = tablet
    tiles = out / "tiles"
    assert json.loads((tiles / "index.json").read_text()) == index
    assert index["faces"] == {f: f"{f}/index.json" for f in faces}
    root = json.loads((tiles / "3d" / "tileset.json").read_text())
    assert root["asset"]["version"] == "1.1" and len(root["root"]["transform"]) == 16
    children = root["root"]["children"]
    assert [c["content"]["uri"] for c in children] == [f"../{f}/3d/tileset.json" for f in faces]
    for child, (folder, (_, matrix)) in zip(children, faces.items(), strict=True):
        face_set = json.loads((tiles / folder / "3d" / "tileset.json").read_text())
        np.testing.assert_allclose(np.array(face_set["root"]["transform"]).reshape(4, 4).T, matrix)
        lo, hi = transformed_box(face_set["root"]["boundingVolume"]["box"], matrix)
        box = np.array(child["boundingVolume"]["box"])
        assert np.all(lo >= box[:3] - np.diag(box[3:].reshape(3, 3)) - 1e-6)
        assert np.all(hi <= box[:3] + np.diag(box[3:].reshape(3, 3)) + 1e-6)
        assert child["geometricError"] == face_set["geometricError"]
        assert json.loads((tiles / folder / "index.json").read_text())["width_px"] > 0
    # The reverse lies behind the obverse in the tablet frame (z away from the camera).
    z = [c["boundingVolume"]["box"][2] for c in children]
    assert z[1] > z[0] + 10


def test_files_json_covers_every_face_file(tablet):
    out, _, index = tablet
    tiles = out / "tiles"
    files = json.loads((tiles / "files.json").read_text())
    top = {tiles / "files.json", tiles / "index.json"}  # written after the list
    on_disk = {p.relative_to(tiles).as_posix() for p in tiles.rglob("*") if p.is_file()}
    on_disk -= {p.relative_to(tiles).as_posix() for p in top}
    assert on_disk == set(files)
    assert "faces/reverse/3d/0/0_0.glb" in files
    assert index["stats"]["tiles_3d"] == sum(1 for n in files if n.endswith(".glb"))


def test_a_tablet_without_faces_is_an_error(tmp_path):
    with pytest.raises(TileError, match="at least one face"):
        build_tablet_tiles(tmp_path, {})
    assert not (tmp_path / "tiles").exists()
