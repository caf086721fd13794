"""Access to the files of a bundle, a directory or a ZIP archive, with safety caps.

Directory members are opened component by component relative to the bundle's root with
``O_NOFOLLOW``, so no symbolic link (at any depth) and nothing but a regular file is ever
read. ZIP members are inflated in chunks while counting bytes: the caps on total
uncompressed size and on compression ratio hold whatever the archive's headers claim.
"""

from __future__ import annotations

import errno
import lzma
import os
import stat
import struct
import threading
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

from worker.bundle.errors import Problem
from worker.bundle.manifest import MANIFEST_NAME as MANIFEST
from worker.bundle.paths import archive_entry_problem

MACOSX = "__MACOSX/"
CHUNK_BYTES = 1 << 20
_ZIP_ERRORS = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    OSError,
    EOFError,
    ValueError,
    NotImplementedError,
    RuntimeError,
    zlib.error,
    lzma.LZMAError,
    struct.error,
)


@dataclass(frozen=True)
class Limits:
    """Safety caps, all keyword arguments of `open_bundle` / `validate_bundle`.

    ``max_ratio`` applies to a ZIP member once it has inflated past ``ratio_floor_bytes``
    (a small, very compressible file is no bomb).
    """

    max_total_bytes: int = 8 << 30
    max_file_bytes: int = 1 << 30
    max_ratio: float = 200.0
    ratio_floor_bytes: int = 1 << 20
    max_manifest_bytes: int = 16 << 20
    max_image_pixels: int = 1 << 26


class ContainerError(Exception):
    """A member cannot be read safely; the message names no path (the caller adds it)."""


class Container:
    """Common interface: `read` a member's bytes (whole or a head), `close`."""

    def __init__(self, limits: Limits):
        self.limits = limits
        self._seen_bytes: dict[str, int] = {}
        self._total_bytes = 0
        self._lock = threading.Lock()  # readers may run in several threads

    def _account(self, name: str, nbytes: int) -> None:
        """Count each member once toward the total cap, however often it is read."""
        with self._lock:
            seen = self._seen_bytes.get(name, 0)
            if nbytes <= seen:
                return
            self._seen_bytes[name] = nbytes
            self._total_bytes += nbytes - seen
            total = self._total_bytes
        if total > self.limits.max_total_bytes:
            raise ContainerError(
                f"bundle holds more than max_total_bytes = {self.limits.max_total_bytes} bytes"
            )

    def read(self, path: str, *, limit: int | None = None) -> bytes:
        raise NotImplementedError

    def close(self) -> None:
        pass


class DirectoryContainer(Container):
    def __init__(self, root: Path, limits: Limits):
        super().__init__(limits)
        self.root = root

    def _open(self, path: str) -> int:
        """fd of the regular file ``path`` under root; no component may be a symbolic link."""
        parts = path.split("/")
        try:
            dir_fd = os.open(self.root, os.O_RDONLY | os.O_DIRECTORY)
        except OSError as exc:
            message = f"cannot be read: the bundle folder is gone ({exc.strerror})"
            raise ContainerError(message) from None
        try:
            for part in parts[:-1]:
                try:
                    fd = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW, dir_fd=dir_fd)
                except OSError as exc:
                    raise _explain(exc, part, folder=True, dir_fd=dir_fd) from None
                os.close(dir_fd)
                dir_fd = fd
            try:
                st = os.stat(parts[-1], dir_fd=dir_fd, follow_symlinks=False)
            except OSError as exc:
                raise _explain(exc, parts[-1], folder=False, dir_fd=dir_fd) from None
            if stat.S_ISLNK(st.st_mode):
                raise ContainerError("is a symbolic link; images must be regular files")
            if not stat.S_ISREG(st.st_mode):
                raise ContainerError("is not a regular file (a directory, pipe or device)")
            # O_NONBLOCK: should the file be swapped for a FIFO meanwhile, open does not hang.
            flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK
            try:
                fd = os.open(parts[-1], flags, dir_fd=dir_fd)
            except OSError as exc:
                raise _explain(exc, parts[-1], folder=False, dir_fd=dir_fd) from None
        finally:
            os.close(dir_fd)
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise ContainerError("is not a regular file")
        return fd

    def read(self, path: str, *, limit: int | None = None) -> bytes:
        fd = self._open(path)
        with os.fdopen(fd, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            cap = self.limits.max_file_bytes
            if limit is None and size > cap:
                raise ContainerError(f"is {size} bytes, more than max_file_bytes = {cap}")
            want = min(size, limit) if limit is not None else size
            self._account(path, want)
            data = fh.read(want)
        return data


def _explain(exc: OSError, part: str, *, folder: bool, dir_fd: int) -> ContainerError:
    if exc.errno == errno.ENOENT:
        return ContainerError("does not exist")
    try:
        is_link = stat.S_ISLNK(os.stat(part, dir_fd=dir_fd, follow_symlinks=False).st_mode)
    except OSError:
        is_link = False
    if is_link or exc.errno == errno.ELOOP:
        return ContainerError(f"goes through a symbolic link ({part!r}); links are not allowed")
    if exc.errno == errno.ENOTDIR:
        return ContainerError(f"{part!r} is not a folder" if folder else "is not a regular file")
    return ContainerError(f"cannot be opened ({exc.strerror})")


class ZipContainer(Container):
    def __init__(
        self, archive: zipfile.ZipFile, prefix: str, limits: Limits, *, archive_bytes: int
    ):
        super().__init__(limits)
        self.archive = archive
        self.prefix = prefix
        self._entries: dict[str, list[zipfile.ZipInfo]] = {}
        self._archive_bytes = archive_bytes
        for info in archive.infolist():
            self._entries.setdefault(info.filename, []).append(info)

    def _info(self, path: str) -> zipfile.ZipInfo:
        infos = self._entries.get(path)
        if not infos:
            folder = self._entries.get(path + "/")
            raise ContainerError("is a folder, not a file" if folder else "does not exist")
        if len(infos) > 1:
            raise ContainerError(f"appears {len(infos)} times in the archive (ambiguous)")
        info = infos[0]
        mode = info.external_attr >> 16
        if info.create_system == 3 and stat.S_IFMT(mode) and not stat.S_ISREG(mode):
            kind = "a symbolic link" if stat.S_ISLNK(mode) else "not a regular file"
            raise ContainerError(f"is {kind} in the archive; images must be regular files")
        if info.is_dir():
            raise ContainerError("is a folder, not a file")
        if info.flag_bits & 0x1:
            raise ContainerError("is encrypted")
        return info

    def read(self, path: str, *, limit: int | None = None) -> bytes:
        name = self.prefix + path
        info = self._info(name)
        lim = self.limits
        cap = lim.max_file_bytes if limit is None else min(limit, lim.max_file_bytes)
        # A lying header cannot buy a larger allowance: no member is larger than the archive.
        compressed = min(info.compress_size, self._archive_bytes)
        ratio_cap = max(lim.max_ratio * compressed, lim.ratio_floor_bytes)
        want = limit if limit is not None else cap + 1
        chunks: list[bytes] = []
        got = 0
        try:
            with self.archive.open(info) as member:
                while got < want:
                    chunk = member.read(min(CHUNK_BYTES, want - got))
                    if not chunk:
                        break
                    got += len(chunk)
                    chunks.append(chunk)
                    if got > ratio_cap:
                        raise ContainerError(
                            f"inflates more than max_ratio = {lim.max_ratio:g} times its "
                            f"compressed size of {compressed} bytes (a zip bomb?)"
                        )
                    if got > cap:
                        raise ContainerError(f"inflates to more than max_file_bytes = {cap}")
                    self._account(name, got)
        except ContainerError:
            raise
        except _ZIP_ERRORS as exc:
            raise ContainerError(f"cannot be read from the archive ({exc})") from None
        return b"".join(chunks)

    def close(self) -> None:
        self.archive.close()


def open_container(
    path: str | os.PathLike, limits: Limits
) -> tuple[Container | None, list[Problem]]:
    """The directory or ZIP at ``path``, or None and the problems that prevent opening it."""
    where = "bundle"
    p = Path(path)
    try:
        if p.is_dir():
            return DirectoryContainer(p, limits), []
        if not p.exists():
            return None, [Problem(where, f"{str(p)!r} does not exist")]
        if not p.is_file():
            return None, [Problem(where, f"{str(p)!r} is neither a folder nor a ZIP file")]
        archive = zipfile.ZipFile(p)
    except _ZIP_ERRORS as exc:
        return None, [Problem(where, f"{str(p)!r} is neither a bundle folder nor a ZIP ({exc})")]
    try:
        prefix, problems = _zip_prefix(archive)
    except _ZIP_ERRORS as exc:
        archive.close()
        return None, [Problem(where, f"{str(p)!r} is a damaged ZIP ({exc})")]
    if prefix is None:
        archive.close()
        return None, problems
    return ZipContainer(archive, prefix, limits, archive_bytes=p.stat().st_size), problems


def _zip_prefix(archive: zipfile.ZipFile) -> tuple[str | None, list[Problem]]:
    """Where manifest.json is: "" (root) or "folder/"; plus problems with hostile entry names."""
    problems = []
    names = [i.filename for i in archive.infolist()]
    for name in names:
        message = archive_entry_problem(name)
        if message:
            problems.append(Problem(f"archive entry {name!r}", message))
    if MANIFEST in names:
        return "", problems
    candidates = sorted(
        {
            n[: -len(MANIFEST)]
            for n in names
            if n.count("/") == 1 and n.endswith("/" + MANIFEST) and not n.startswith(MACOSX)
        }
    )
    if len(candidates) == 1:
        return candidates[0], problems
    if candidates:
        listed = ", ".join(candidates)
        message = (
            f"holds manifest.json in several top-level folders ({listed}); which is the bundle?"
        )
    else:
        message = "has no manifest.json at its root or inside exactly one top-level folder"
    return None, [*problems, Problem("bundle", f"the ZIP {message}")]
