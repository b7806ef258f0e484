"""``cellcal/result@1`` stays readable: documents that an earlier cellcal wrote (with the code
of commit 1586076, ``cellcal calibrate`` on simulated station sets) still load, keep every
field, export to every format that applies and give a report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from calib.result import parse_result
from service.exports import CAMERA_FORMATS, FORMATS, TRANSFORM_FORMATS, export
from service.results.report import render_report

DATA = Path(__file__).parent / "data"
#: Documents written by an earlier version and the export formats each one supports.
WRITTEN_BEFORE = {
    "result-1586076-images.json": FORMATS,
    "result-1586076-pose-only.json": ("json", *TRANSFORM_FORMATS),
}


@pytest.mark.parametrize("name", sorted(WRITTEN_BEFORE))
def test_an_earlier_document_loads_whole(name: str) -> None:
    doc = json.loads((DATA / name).read_text())
    result = parse_result(doc, name)
    assert result.document() == doc
    assert result.format == "cellcal/result@1" and result.quality is not None


@pytest.mark.parametrize("name", sorted(WRITTEN_BEFORE))
def test_an_earlier_document_exports_and_reports(name: str) -> None:
    result = parse_result(json.loads((DATA / name).read_text()), name)
    for fmt in WRITTEN_BEFORE[name]:
        content, _media, filename = export(result, fmt)
        assert content and filename, fmt
    if result.camera is None:
        for fmt in CAMERA_FORMATS:
            with pytest.raises(ValueError):
                export(result, fmt)
    page = render_report(result.document())
    assert result.quality is not None and result.quality.verdict in page
