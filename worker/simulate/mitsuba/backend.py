"""Import Mitsuba 3 with a CPU variant, or say clearly why it cannot be used.

``llvm_ad_rgb`` (vectorised, JIT-compiled by Dr.Jit through libLLVM) is 3-4x faster than
``scalar_rgb`` at 64 samples per pixel on this machine (docs/simulator.md, "Mitsuba"),
but Dr.Jit needs a libLLVM it can compile with: LLVM 15 aborts the process on an
``fminimum`` it cannot select (no exception to catch), so ``auto`` points Dr.Jit at a
libLLVM >= 17 (Debian's ``libllvm19``) and otherwise falls back to ``scalar_rgb``.
"""

from __future__ import annotations

import glob
import os
import re

__all__ = ["VARIANTS", "MitsubaUnavailable", "load_mitsuba"]

VARIANTS = ("auto", "llvm_ad_rgb", "scalar_rgb")
_MIN_LLVM = 17


class MitsubaUnavailable(RuntimeError):
    """Mitsuba 3 (the optional extra ``mitsuba``) is not installed or has no usable variant."""


def _newest_libllvm() -> str | None:
    """Path of the newest libLLVM >= _MIN_LLVM in the system library folders, else None."""
    best: tuple[int, str] | None = None
    for path in glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/libLLVM*.so*"):
        m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
        if m and int(m.group(1)) >= _MIN_LLVM and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), path)
    return best[1] if best else None


def load_mitsuba(variant: str = "auto"):
    """``(mitsuba module, variant name)`` with the variant set; MitsubaUnavailable if not."""
    if variant not in VARIANTS:
        raise ValueError(f"variant: unknown {variant!r}; choose from {list(VARIANTS)}")
    requested = variant
    if variant in ("auto", "llvm_ad_rgb") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        lib = _newest_libllvm()
        if lib is None and variant == "llvm_ad_rgb":
            raise MitsubaUnavailable(
                f"variant llvm_ad_rgb needs libLLVM >= {_MIN_LLVM} (apt-get install libllvm19)"
            )
        if lib is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib  # read once, when drjit is first imported
        elif variant == "auto":
            variant = "scalar_rgb"
    try:
        import mitsuba as mi
    except ImportError:
        raise MitsubaUnavailable(
            "the mitsuba renderer needs Mitsuba 3: pip install 'digital-hammurabi[mitsuba]' "
            "(or make setup)"
        ) from None
    if variant == "auto":
        variant = "llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb"
    try:
        mi.set_variant(variant)
        if variant.startswith("llvm"):
            import drjit as dr

            if not dr.has_backend(dr.JitBackend.LLVM):
                raise ImportError("Dr.Jit found no LLVM backend")
    except (ImportError, AttributeError) as exc:
        if requested == "auto" and "scalar_rgb" in mi.variants():
            mi.set_variant("scalar_rgb")
            return mi, "scalar_rgb"
        raise MitsubaUnavailable(f"mitsuba: cannot use variant {variant}: {exc}") from None
    return mi, variant
