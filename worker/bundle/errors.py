"""Problems found in a scan bundle, and the exception that carries them."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class Problem:
    """One violation of SCAN_BUNDLE.md.

    ``where`` names the culprit: a manifest field (``frames[17].period_um``), a file
    (``images/p00.png``) or the container (``bundle``); ``message`` says what is wrong.
    """

    where: str
    message: str

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"


class BundleError(ValueError):
    """A bundle (or the input of ``write_bundle``) breaks the spec; ``problems`` lists every issue."""

    def __init__(self, problems: Iterable[Problem]):
        self.problems: list[Problem] = list(problems)
        if not self.problems:
            raise ValueError("BundleError needs at least one Problem")
        shown = "\n".join(f"  {p}" for p in self.problems[:50])
        more = len(self.problems) - 50
        tail = f"\n  ... and {more} more" if more > 0 else ""
        n = len(self.problems)
        super().__init__(
            f"invalid scan bundle ({n} problem{'s' if n != 1 else ''}):\n{shown}{tail}"
        )
