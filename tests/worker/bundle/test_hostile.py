"""Hostile and broken input: every case ends in Problems naming the culprit, never a crash."""

from __future__ import annotations

import io
import json
import os
import stat
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from worker.bundle import BundleError, open_bundle, validate_bundle


def _zip(path: Path, entries: list[tuple[str | zipfile.ZipInfo, bytes]], *, deflate=False) -> Path:
    method = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=method) as archive:
        for name, data in entries:
            archive.writestr(name, data)
    return path


def _entries(bundle_dir: Path, prefix: str = "") -> list[tuple[str, bytes]]:
    return [
        (prefix + str(p.relative_to(bundle_dir)), p.read_bytes())
        for p in sorted(bundle_dir.rglob("*"))
        if p.is_file()
    ]


def _only(problems, where: str) -> str:
    assert [p.where for p in problems] == [where], problems
    return problems[0].message


# --- paths and links in a directory bundle ------------------------------------------------


def test_symlink_out_of_the_bundle(written_bundle, tmp_path) -> None:
    path = written_bundle()
    secret = tmp_path / "secret.png"
    secret.write_bytes((path / "dark.png").read_bytes())  # a perfectly good image, outside
    (path / "dark.png").unlink()
    (path / "dark.png").symlink_to(secret)
    assert "symbolic link" in _only(validate_bundle(path), "dark.png")


def test_symlink_inside_the_bundle(written_bundle) -> None:
    path = written_bundle()
    (path / "dark.png").unlink()
    (path / "dark.png").symlink_to("object/p0.png")
    assert "symbolic link" in _only(validate_bundle(path), "dark.png")


def test_symlinked_folder(written_bundle, tmp_path) -> None:
    path = written_bundle()
    (path / "object").rename(tmp_path / "elsewhere")
    (path / "object").symlink_to(tmp_path / "elsewhere")
    problems = validate_bundle(path)
    assert {p.where for p in problems} == {f"object/{n}" for n in _object_names()}
    assert all("symbolic link ('object')" in p.message for p in problems)


def _object_names() -> list[str]:
    return ["p0.png", "p90.png", "red.png", "f0.png", "f90.png", "f180.png", "f270.png"]


def test_symlinked_manifest(written_bundle, tmp_path) -> None:
    path = written_bundle()
    (path / "manifest.json").rename(tmp_path / "m.json")
    (path / "manifest.json").symlink_to(tmp_path / "m.json")
    assert "symbolic link" in _only(validate_bundle(path), "manifest.json")


def test_fifo_and_folder_are_not_images(written_bundle) -> None:
    path = written_bundle()
    (path / "dark.png").unlink()
    os.mkfifo(path / "dark.png")  # opening it for reading must not hang
    (path / "object/p0.png").unlink()
    (path / "object/p0.png").mkdir()
    problems = {p.where: p.message for p in validate_bundle(path)}
    assert set(problems) == {"dark.png", "object/p0.png"}
    assert all("not a regular file" in m for m in problems.values())


def test_missing_image_and_missing_manifest(written_bundle) -> None:
    path = written_bundle()
    (path / "object/p0.png").unlink()
    assert "does not exist" in _only(validate_bundle(path), "object/p0.png")
    (path / "manifest.json").unlink()
    assert "does not exist" in _only(validate_bundle(path), "manifest.json")


def test_missing_path_and_non_bundle_file(tmp_path) -> None:
    assert "does not exist" in _only(validate_bundle(tmp_path / "nope"), "bundle")
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"PK\x03\x04 this is not really a zip")
    assert "neither a bundle folder nor a ZIP" in _only(validate_bundle(junk), "bundle")
    with pytest.raises(BundleError, match="bundle: "):
        open_bundle(junk)


def test_corrupt_zip(written_bundle) -> None:
    path = written_bundle(as_zip=True)
    data = bytearray(path.read_bytes())
    end = data.rfind(b"PK\x05\x06")
    data[end + 16 : end + 20] = struct.pack("<I", 3)  # central directory offset: garbage
    path.write_bytes(bytes(data))
    assert "cannot be read from the archive" in _only(validate_bundle(path), "manifest.json")
    path.write_bytes(bytes(data[: len(data) // 2]))  # truncated: no central directory
    assert "neither a bundle folder nor a ZIP" in _only(validate_bundle(path), "bundle")


@pytest.mark.parametrize(
    "bad", ["../dark.png", "/tmp/dark.png", "C:/dark.png", "object\\p0.png", "dark\x00.png"]
)
def test_unsafe_manifest_paths_are_never_opened(written_bundle, bad) -> None:
    path = written_bundle()
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["frames"][0]["file"] = bad
    (path / "manifest.json").write_text(json.dumps(manifest))
    problems = validate_bundle(path)
    assert [p.where for p in problems] == ["frames[0].file"]


# --- ZIP archives ----------------------------------------------------------------------------


def test_zip_with_a_top_level_folder_and_macosx_junk(written_bundle, tmp_path) -> None:
    entries = _entries(written_bundle(), "scan-42/")
    entries += [("__MACOSX/scan-42/._manifest.json", b"\x00\x05junk"), ("__MACOSX/._x", b"")]
    entries += [("__MACOSX/manifest.json", b"not json")]
    path = _zip(tmp_path / "folder.zip", entries)
    assert validate_bundle(path) == []
    with open_bundle(path) as bundle:
        assert bundle.raw(0).shape == (12, 16)


def test_zip_with_two_candidate_folders_or_none(written_bundle, tmp_path) -> None:
    base = written_bundle()
    both = _zip(tmp_path / "two.zip", _entries(base, "a/") + _entries(base, "b/"))
    assert "several top-level folders (a/, b/)" in _only(validate_bundle(both), "bundle")
    deep = _zip(tmp_path / "deep.zip", _entries(base, "a/b/"))
    assert "no manifest.json" in _only(validate_bundle(deep), "bundle")


def test_zip_slip_entries_are_reported(written_bundle, tmp_path) -> None:
    entries = _entries(written_bundle())
    for name in ("../evil.png", "/etc/evil", "C:\\evil", "a/..\\..\\evil"):
        entries.append((name, b"x"))
    path = _zip(tmp_path / "slip.zip", entries)
    problems = validate_bundle(path)
    assert [p.where for p in problems] == [
        "archive entry '../evil.png'",
        "archive entry '/etc/evil'",
        "archive entry 'C:\\\\evil'",
        "archive entry 'a/..\\\\..\\\\evil'",
    ]


def test_zip_symlink_entry(written_bundle, tmp_path) -> None:
    entries: list = [e for e in _entries(written_bundle()) if e[0] != "dark.png"]
    link = zipfile.ZipInfo("dark.png")
    link.create_system = 3
    link.external_attr = (stat.S_IFLNK | 0o777) << 16
    entries.append((link, b"/etc/passwd"))
    path = _zip(tmp_path / "link.zip", entries)
    assert "symbolic link" in _only(validate_bundle(path), "dark.png")


def test_zip_duplicate_entries(written_bundle, tmp_path) -> None:
    entries = _entries(written_bundle())
    entries.append(("dark.png", dict(entries)["object/p0.png"]))
    with pytest.warns(UserWarning, match="Duplicate name"):
        path = _zip(tmp_path / "dup.zip", entries)
    assert "appears 2 times" in _only(validate_bundle(path), "dark.png")


def _patch_header_field(path: Path, name: bytes, *, local_at: int, central_at: int, value: int):
    """Set a 2-byte field of ``name``'s local and central ZIP headers."""
    data = bytearray(path.read_bytes())
    for signature, at, len_at, name_at in (
        (b"PK\x03\x04", local_at, 26, 30),
        (b"PK\x01\x02", central_at, 28, 46),
    ):
        start = 0
        while (start := data.find(signature, start)) >= 0:
            (name_len,) = struct.unpack_from("<H", data, start + len_at)
            if data[start + name_at : start + name_at + name_len] == name:
                struct.pack_into("<H", data, start + at, value)
            start += 4
    path.write_bytes(bytes(data))


def test_zip_encrypted_and_unsupported_members(written_bundle) -> None:
    path = written_bundle(as_zip=True)
    _patch_header_field(path, b"dark.png", local_at=6, central_at=8, value=1)  # encrypted flag
    _patch_header_field(path, b"object/p0.png", local_at=8, central_at=10, value=9)  # deflate64
    problems = {p.where: p.message for p in validate_bundle(path)}
    assert set(problems) == {"dark.png", "object/p0.png"}
    assert "encrypted" in problems["dark.png"]
    assert "cannot be read from the archive" in problems["object/p0.png"]


def _bomb_bundle(written_bundle, tmp_path: Path, *, zero_bytes: int) -> Path:
    """A valid bundle whose dark frame is a PNG followed by ``zero_bytes`` zeros (deflated)."""
    entries = _entries(written_bundle())
    entries = [(n, d + bytes(zero_bytes) if n == "dark.png" else d) for n, d in entries]
    return _zip(tmp_path / "bomb.zip", entries, deflate=True)


def test_zip_bomb_ratio_is_checked_while_inflating(written_bundle, tmp_path) -> None:
    path = _bomb_bundle(written_bundle, tmp_path, zero_bytes=8 << 20)
    message = _only(validate_bundle(path), "dark.png")
    assert "inflates more than max_ratio = 200 times" in message
    # The same archive passes when the caller allows a higher ratio.
    assert validate_bundle(path, max_ratio=1e6) == []


def test_zip_total_size_cap(written_bundle) -> None:
    path = written_bundle(as_zip=True)
    problems = validate_bundle(path, max_total_bytes=6000)
    assert problems and all("max_total_bytes = 6000" in p.message for p in problems)


def _patch_sizes(path: Path, name: bytes, *, file_size: int) -> None:
    """Rewrite the uncompressed size of ``name`` in its local and central headers."""
    data = bytearray(path.read_bytes())
    # (signature, offset of the uncompressed size, of the name length, of the name)
    for signature, size_at, len_at, name_at in (
        (b"PK\x03\x04", 22, 26, 30),
        (b"PK\x01\x02", 24, 28, 46),
    ):
        start = 0
        while (start := data.find(signature, start)) >= 0:
            (name_len,) = struct.unpack_from("<H", data, start + len_at)
            if data[start + name_at : start + name_at + name_len] == name:
                struct.pack_into("<I", data, start + size_at, file_size)
            start += 4
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("claimed", [100, 0xFFFFFFF0])
def test_zip_lying_headers(written_bundle, tmp_path, claimed) -> None:
    path = _bomb_bundle(written_bundle, tmp_path, zero_bytes=8 << 20)
    _patch_sizes(path, b"dark.png", file_size=claimed)
    problems = validate_bundle(path)
    assert [p.where for p in problems] == ["dark.png"], problems


# --- image files -----------------------------------------------------------------------------


def _png_header(width: int, height: int, depth: int = 16, color: int = 0) -> bytes:
    body = b"IHDR" + struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + body + struct.pack(">I", zlib.crc32(body))


def _tiff_header(width: int, height: int) -> bytes:
    """A little-endian uint16 TIFF with one IFD and no pixel data to speak of."""
    tags = [(256, 4, width), (257, 4, height), (258, 3, 16), (259, 3, 1), (262, 3, 1),
            (273, 4, 8), (277, 3, 1), (278, 4, height), (279, 4, min(width * height * 2, 2**32 - 1))]  # fmt: skip
    ifd = struct.pack("<H", len(tags))
    for tag, kind, value in tags:
        ifd += struct.pack("<HHI", tag, kind, 1) + struct.pack("<I", value)
    return b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0)


@pytest.mark.parametrize("header", [_png_header(200_000, 200_000), _tiff_header(100_000, 90_000)])
def test_huge_dimensions_are_refused_before_decoding(written_bundle, header) -> None:
    path = written_bundle()
    (path / "dark.png").write_bytes(header + bytes(64))
    message = _only(validate_bundle(path), "dark.png")
    assert "more than max_image_pixels" in message


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        (b"hello, I am text", "not a PNG or TIFF"),
        (b"", "not a PNG or TIFF"),
        (_png_header(16, 12)[:20], "truncated"),
        (_png_header(16, 12), "cannot be decoded"),
        (_png_header(16, 12, color=2), "RGB PNG"),
        (_png_header(16, 12, depth=4), "4-bit PNG"),
        (_png_header(16, 12)[:-1] + b"\x00", "checksum"),
        (_png_header(32, 12), "is 32×12 pixels, not camera.width × camera.height = 16×12"),
        (_tiff_header(16, 12)[:30], "not a readable TIFF"),
        (b"II*\x00" + bytes(4), "TIFF of 0 pages"),
    ],
)
def test_broken_images(written_bundle, content: bytes, fragment: str) -> None:
    path = written_bundle()
    (path / "object/p90.png").write_bytes(content)
    assert fragment in _only(validate_bundle(path), "object/p90.png")


def test_truncated_png_is_found_when_decoding(written_bundle) -> None:
    path = written_bundle()
    data = (path / "object/p90.png").read_bytes()
    (path / "object/p90.png").write_bytes(data[: len(data) // 2])
    with open_bundle(path) as bundle, pytest.raises(BundleError, match="object/p90.png"):
        bundle.radiance(2)
    assert "cannot be decoded" in _only(validate_bundle(path), "object/p90.png")


def test_rgb_and_multipage_tiff(written_bundle) -> None:
    import tifffile

    path = written_bundle()
    rgb, pages = io.BytesIO(), io.BytesIO()
    tifffile.imwrite(rgb, np.zeros((12, 16, 3), np.uint8), photometric="rgb")
    tifffile.imwrite(pages, np.zeros((2, 12, 16), np.uint16))
    (path / "object/p0.png").write_bytes(rgb.getvalue())
    (path / "object/p90.png").write_bytes(pages.getvalue())
    problems = {p.where: p.message for p in validate_bundle(path)}
    assert "3 samples per pixel" in problems["object/p0.png"]
    assert "2 pages" in problems["object/p90.png"]


def test_non_finite_float_tiff(written_bundle) -> None:
    import tifffile

    path = written_bundle()
    values = np.zeros((12, 16), np.float32)
    values[1, 2], values[3, 4] = np.nan, np.inf
    buf = io.BytesIO()
    tifffile.imwrite(buf, values)
    (path / "object/p0.png").write_bytes(buf.getvalue())
    assert "2 NaN or infinite values" in _only(validate_bundle(path), "object/p0.png")


def test_manifest_too_large_or_not_an_object(written_bundle) -> None:
    path = written_bundle()
    (path / "manifest.json").write_bytes(b" " * (16 << 20) + b"{}")
    assert "more than the cap" in _only(validate_bundle(path), "manifest.json")
    (path / "manifest.json").write_text("[1, 2]")
    assert "must hold a JSON object" in _only(validate_bundle(path), "manifest.json")


def test_all_problems_are_reported_together(written_bundle) -> None:
    path = written_bundle()
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["frames"][1]["azimuth_deg"] = float("nan")  # becomes NaN in the file
    manifest["camera"]["pixel_size_um"] = 0
    (path / "manifest.json").write_text(json.dumps(manifest))
    assert "NaN" in _only(validate_bundle(path), "manifest.json")
    del manifest["frames"][1]["azimuth_deg"]
    (path / "manifest.json").write_text(json.dumps(manifest))
    (path / "object/p90.png").write_bytes(b"junk")
    assert {p.where for p in validate_bundle(path)} == {
        "camera.pixel_size_um",
        "frames[1].azimuth_deg",
        "object/p90.png",
    }


def test_zip_entry_problems_do_not_hide_frame_problems(written_bundle, tmp_path) -> None:
    entries = dict(_entries(written_bundle()))
    manifest = json.loads(entries["manifest.json"])
    manifest["frames"][7]["phase_deg"] = 45  # breaks the object fringe set
    entries["manifest.json"] = json.dumps(manifest).encode()
    path = _zip(tmp_path / "both.zip", [*entries.items(), ("../evil", b"")])
    problems = validate_bundle(path)
    assert [p.where for p in problems][:2] == ["archive entry '../evil'", "frames[4]"]
