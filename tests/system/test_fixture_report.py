"""The browser tests' synthetic face model writes report.json as the pipeline does.

worker/pipeline.py writes ``image_size`` as ``{"width": W, "height": H}``; the readers of a
model's report (the annotation API's image grid, the IIIF manifest) only understand that form,
so a fixture in another form would hide their code paths from the browser tests."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent / "browser" / "synthetic_model.py"


def _synthetic_model():
    spec = importlib.util.spec_from_file_location("hammurabi_synthetic_model_report", HERE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_fixture_report_image_size_is_the_pipelines_form(tmp_path):
    from backend.api import annotations, iiif

    facts = _synthetic_model().make_model_dir(tmp_path / "m")
    report = json.loads((tmp_path / "m" / "report.json").read_text())
    rows, cols = np.load(tmp_path / "m" / "height.npy").shape
    assert report["image_size"] == {"width": cols, "height": rows}
    assert (facts.width_px, facts.height_px) == (cols, rows)
    # Both readers of the report find the grid (they return None for any other form).
    assert iiif._grid(report) == (cols, rows, facts.pixel_size_um)

    class _Model:
        pass

    model = _Model()
    model.report = report
    assert annotations._grid(model) == (cols, rows, facts.pixel_size_um)
