"""Captures: the typed model, loaders for a folder or zip, safe extraction and validation.

Format and every check: docs/capture-format.md.
"""

from neumatex_core.capture.archive import extract_zip
from neumatex_core.capture.loader import load_capture
from neumatex_core.capture.model import Capture, CaptureError, Frame, Problem
from neumatex_core.capture.report import run_validate
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.capture.validate import validate_capture

__all__ = [
    "Capture",
    "CaptureError",
    "Frame",
    "Problem",
    "Tonemap",
    "extract_zip",
    "load_capture",
    "run_validate",
    "validate_capture",
]
