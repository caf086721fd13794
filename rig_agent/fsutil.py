"""The spool's durable writes: whole files through `worker.durable`, plus a fsynced journal."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from worker.durable import write_file_atomic


def atomic_write_json(path: Path, data: Any) -> None:
    text = json.dumps(data, indent=2, sort_keys=True, allow_nan=False)
    write_file_atomic(path, text.encode("utf-8") + b"\n")


def append_line_durable(path: Path, line: str) -> None:
    """Append one line and fsync; a torn last line is ignored by readers of the file."""
    if "\n" in line:
        raise ValueError("line must not contain a newline")
    with open(path, "a", encoding="utf-8") as handle:
        handle.write(line + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def read_json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))
