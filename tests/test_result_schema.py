"""The typed result document (``calib.result``): what cellcal writes validates and
has no field the schema does not declare, minimal and older documents validate, bad ones are
refused in one line, and the OpenAPI document shows the result's fields."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from calib.result import Result, parse_result
from service.app import create_app
from service.results.document import calibration_result
from tests.support.helpers import undeclared_fields
from tests.support.results import full_result, intrinsics_only_result, pose_only_result
from tests.support.service import settings
from tests.support.stations import calibrate, detections


def test_a_real_intrinsics_only_result_validates_with_every_field_declared() -> None:
    written = calibration_result(calibrate(detections(), None), command="test")
    doc = json.loads(json.dumps(written.document()))
    result = parse_result(doc)
    assert result.camera is not None and result.hand_eye is None and result.target_pose is None
    assert result.stations is not None and len(result.stations) == 15
    assert undeclared_fields(result) == []
    assert result.document() == doc


@pytest.mark.parametrize("make", [full_result, pose_only_result, intrinsics_only_result])
def test_the_documents_the_tests_store_validate_and_read_back_unchanged(make: Any) -> None:
    doc = json.loads(json.dumps(make()))
    result = parse_result(doc)
    assert undeclared_fields(result) == []
    assert result.document() == doc  # nothing added: fields the document lacks stay absent


def test_pose_only_results_have_no_camera() -> None:
    result = parse_result(pose_only_result())
    assert result.camera is None and result.hand_eye is not None
    assert result.method == "sm" and result.motions is not None


def test_unknown_fields_are_kept() -> None:
    doc = {**full_result(), "added_in_a_later_version": {"x": 1}}
    assert parse_result(doc).document()["added_in_a_later_version"] == {"x": 1}


@pytest.mark.parametrize("change, message", [
    ({"setup": "eye_on_hand"}, "setup: Input should be 'eye_in_hand' or 'eye_to_hand'"),
    ({"format": "cellcal/result@2"}, "format: Input should be 'cellcal/result@1'"),
    ({"camera": {"image_size": [640, 480], "K": [[1, 0, 0], [0, 1, 0]], "dist": []}},
     "camera.K: List should have at least 3 items"),
    ({"hand_eye": {"matrix": [[1, 0, 0, 0]] * 3}}, "hand_eye.matrix: List should have at "
                                                   "least 4 items"),
])
def test_bad_documents_are_refused_in_one_line(change: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=r"^result: not a cellcal/result@1 document: ") as err:
        parse_result({**full_result(), **change})
    assert message in str(err.value) and "\n" not in str(err.value)


def test_missing_required_blocks_are_named() -> None:
    doc = full_result()
    del doc["camera"], doc["hand_eye"]
    with pytest.raises(ValueError, match=r"camera: Field required \(and 1 more problems\)$"):
        parse_result(doc)


def test_openapi_documents_the_result(tmp_path: Path) -> None:
    with TestClient(create_app(settings(tmp_path))) as client:
        doc = client.get("/openapi.json").json()
    schemas = doc["components"]["schemas"]
    result_ref = schemas["CalibrationPublic"]["properties"]["result"]["anyOf"][0]["$ref"]
    result = schemas[result_ref.rsplit("/", 1)[1]]
    assert set(Result.model_fields) <= set(result["properties"])
    assert set(result["required"]) == {"format", "setup", "camera", "target", "hand_eye",
                                       "target_pose"}
    camera = schemas["CameraModel"]["properties"]
    assert camera["K"]["minItems"] == camera["K"]["maxItems"] == 3
    assert schemas["QualityBlock"]["properties"]["verdict"]["enum"] == ["pass", "warn", "fail"]
