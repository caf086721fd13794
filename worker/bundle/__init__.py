"""The one implementation of SCAN_BUNDLE.md v1: validate, read (radiance) and write bundles.

See docs/bundle.md for the CLI (``python -m worker.bundle validate PATH``) and the API.
"""

from worker.bundle.container import Limits
from worker.bundle.errors import BundleError, Problem
from worker.bundle.manifest import (
    Camera,
    Frame,
    Manifest,
    Reference,
    Scan,
    Source,
    is_simulated,
)
from worker.bundle.reader import Bundle, open_bundle, validate_bundle
from worker.bundle.writer import write_bundle

__all__ = [
    "Bundle",
    "BundleError",
    "Camera",
    "Frame",
    "Limits",
    "Manifest",
    "Problem",
    "Reference",
    "Scan",
    "Source",
    "is_simulated",
    "open_bundle",
    "validate_bundle",
    "write_bundle",
]
