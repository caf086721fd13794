"""Relative POSIX paths inside a bundle (SCAN_BUNDLE.md, "Container")."""

from __future__ import annotations

import re

_DRIVE = re.compile(r"^[A-Za-z]:")
MAX_PATH_CHARS = 4096  # PATH_MAX on Linux; also keeps messages that quote a path short


def path_problem(path: str) -> str | None:
    """Why ``path`` may not name a file of a bundle, or None when it may.

    Invalid per the spec: ``..`` segments, a leading ``/``, a drive letter, a backslash or a
    NUL. Also refused: the empty path, paths that name no file (only ``.`` or ``/``), paths
    longer than 4096 characters and strings that are not valid Unicode.
    """
    if not isinstance(path, str):
        return "must be a string (a relative POSIX path)"
    if path == "":
        return "must not be empty"
    if len(path) > MAX_PATH_CHARS:
        return f"is {len(path)} characters long, more than {MAX_PATH_CHARS}"
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return f"{path!r}: is not valid Unicode (holds a lone surrogate)"
    if "\x00" in path:
        return "must not contain a NUL character"
    if "\\" in path:
        return f"{path!r}: must not contain a backslash (use '/')"
    if path.startswith("/"):
        return f"{path!r}: must be relative, not start with '/'"
    if _DRIVE.match(path):
        return f"{path!r}: must not start with a drive letter"
    segments = path.split("/")
    if ".." in segments:
        return f"{path!r}: must not contain '..'"
    if not [s for s in segments if s not in ("", ".")] or path.endswith("/"):
        return f"{path!r}: does not name a file"
    return None


def normalize_path(path: str) -> str:
    """``a/./b//c.png`` -> ``a/b/c.png``; call only on paths for which `path_problem` is None."""
    return "/".join(s for s in path.split("/") if s not in ("", "."))


def archive_entry_problem(name: str) -> str | None:
    """Why a ZIP entry name is hostile (zip-slip, absolute, drive letter, NUL), or None."""
    if "\x00" in name:
        return "entry name contains a NUL character"
    if name.startswith(("/", "\\")) or _DRIVE.match(name):
        return "entry name is absolute"
    if ".." in re.split(r"[/\\]", name):
        return "entry name contains '..' (zip-slip)"
    return None
