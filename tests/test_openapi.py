"""The OpenAPI document declares the error answers the service really sends: every error
status of every operation carries the one JSON error body ``{"detail", "code"}`` (``errors``
for 422), and real answers of each kind validate against it."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import jsonschema_rs
import pytest
from fastapi.testclient import TestClient
from pydantic import BaseModel, ValidationError

from service.api.openapi import ErrorBody
from service.app import create_app
from service.schemas import CheckCreate, RunCreate
from tests.support.service import AUTH, settings

ERROR_REF = {"$ref": "#/components/schemas/ErrorBody"}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with TestClient(create_app(settings(tmp_path_factory.mktemp("openapi")))) as c:
        yield c


@pytest.fixture(scope="module")
def doc(client: TestClient) -> dict[str, Any]:
    return client.get("/openapi.json").json()


def operations(doc: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            yield method, path, op


def test_every_error_status_has_the_error_body(doc: dict[str, Any]) -> None:
    errors = [(m, p, s) for m, p, op in operations(doc) for s in op["responses"]
              if int(s) >= 400]
    assert len(errors) > 100
    for method, path, status in errors:
        schema = doc["paths"][path][method]["responses"][status]["content"][
            "application/json"]["schema"]
        assert schema == ERROR_REF, (method, path, status)
    assert "HTTPValidationError" not in doc["components"]["schemas"]


def test_each_operation_declares_the_statuses_it_can_answer(doc: dict[str, Any]) -> None:
    for method, path, op in operations(doc):
        statuses = set(op["responses"])
        assert {"500", "503"} <= statuses, (method, path)
        if path != "/health":
            assert {"401", "422"} <= statuses, (method, path)
        assert "{" not in path or "404" in statuses, (method, path)
        assert ("413" in statuses) == ("requestBody" in op), (method, path)


#: The document's component names. A client generated from the document names its types by
#: them, so renaming one breaks the client's code: change this list only on purpose (and say so
#: in docs/architecture.md, "The OpenAPI document").
COMPONENTS = [
    "ActivationPublic", "ActiveCalibration", "BoardScale",
    "Body_post_station_runs__run_id__stations_post", "CalibrationCreate", "CalibrationOptions",
    "CalibrationPage", "CalibrationPublic", "CalibrationSummary", "CameraInfo", "CameraModel",
    "Candidate", "CharucoTarget", "CheckCreate", "CheckerboardTarget", "ColdStartPublic",
    "Created", "CrossValidationBlock", "DetectionPublic", "DevicesPublic", "ErrorBody",
    "ErrorInfo", "ErrorItem", "Finding", "Health", "HeldOutStation", "ModelSelection",
    "Motions", "QualityBlock", "Rejected", "Result", "RobotInfo", "RunCreate", "RunPublic",
    "SigmaPoint", "Software", "StationError", "StationFit", "StationPublic", "StopRule",
    "Transform", "Uncertainty", "ValidationCreate", "ValidationPublic",
]


def test_component_names_stay(doc: dict[str, Any]) -> None:
    assert sorted(doc["components"]["schemas"]) == COMPONENTS


def test_starts_declare_the_idempotency_key(doc: dict[str, Any]) -> None:
    """The header the idempotency middleware reads is in the document, on exactly the four
    operations that start work, with the 400 a malformed key gets."""
    starts = sorted((m, p) for m, p, op in operations(doc)
                    if any(q["name"] == "Idempotency-Key" and q["in"] == "header"
                           for q in op.get("parameters", ())))
    assert starts == [("post", "/calibrations/{cal_id}/checks"),
                      ("post", "/calibrations/{cal_id}/validations"),
                      ("post", "/runs"), ("post", "/runs/{run_id}/calibrations")]
    assert all({"400", "409"} <= set(doc["paths"][p][m]["responses"]) for m, p in starts)


@dataclass(frozen=True)
class Case:
    """A request that fails, the operation's path template and the status it gets."""

    method: str
    path: str
    template: str
    status: int
    kwargs: dict[str, Any] = field(default_factory=dict)


@pytest.mark.parametrize("case", [
    Case("get", "/runs", "/runs", 401, {"headers": {}}),
    Case("get", "/runs/nope", "/runs/{run_id}", 404),
    Case("post", "/runs", "/runs", 422, {"json": {"stations": 2}}),
    Case("get", "/calibrations?limit=0", "/calibrations", 422),
    Case("post", "/calibrations/nope/checks", "/calibrations/{cal_id}/checks", 422,
         {"json": {"stations": 0}}),
    Case("get", "/calibrations/active", "/calibrations/active", 404),
    Case("post", "/runs", "/runs", 400,
         {"json": {"stations": 5}, "headers": {**AUTH, "Idempotency-Key": "two words"}}),
], ids=lambda c: f"{c.status}-{c.method}-{c.path}")
def test_real_error_answers_match_the_document(client: TestClient, doc: dict[str, Any],
                                               case: Case) -> None:
    r = client.request(case.method, case.path, **{"headers": AUTH, **case.kwargs})
    assert r.status_code == case.status, r.text
    assert str(case.status) in doc["paths"][case.template][case.method]["responses"]
    body = ErrorBody.model_validate(r.json())
    assert body.detail and body.code
    assert (body.errors is not None) == (case.status == 422)
    assert set(r.json()) <= set(ErrorBody.model_fields)


def test_error_body_schema_is_the_model(doc: dict[str, Any]) -> None:
    schema = doc["components"]["schemas"]["ErrorBody"]
    assert schema["required"] == ["detail", "code"]
    assert set(schema["properties"]) == {"detail", "code", "errors"}
    assert "ErrorItem" in doc["components"]["schemas"]


def test_page_and_docs_are_not_operations(doc: dict[str, Any]) -> None:
    assert not any(p.startswith(("/ui", "/docs", "/redoc")) or p == "/" for p in doc["paths"])


def body_schema(doc: dict[str, Any], name: str) -> jsonschema_rs.Validator:
    """A validator of the document's request body schema ``name`` (references resolved in
    the document)."""
    return jsonschema_rs.validator_for({"$ref": f"#/components/schemas/{name}",
                                        "components": doc["components"]})


def _accepts(model: type[BaseModel], body: dict[str, Any]) -> bool:
    """Whether the service's request model takes ``body``."""
    try:
        model.model_validate(body)
    except ValidationError:
        return False
    return True


RUN_BODIES = [
    {"stations": 5}, {"mode": "robot", "stations": 5, "poses": None}, {"poses": [[0.1] * 6]},
    {"mode": "external"}, {"mode": "external", "stations": None},
    {}, {"mode": "robot"}, {"stations": 5, "poses": [[0.1] * 6]},
    {"mode": "external", "stations": 5}, {"mode": "external", "poses": [[0.1] * 6]},
    {"stations": None, "poses": None}, {"mode": "fast", "stations": 5},
    {"tolerance_mm": 0.5, "tolerance_deg": 0.05}, {"tolerance_mm": 0.5},
    {"tolerance_mm": 0.5, "tolerance_deg": 0.05, "max_stations": 30},
    {"tolerance_deg": 0.05, "max_stations": 30}, {"stations": 5, "max_stations": 30},
    {"stations": 5, "tolerance_mm": 0.5, "tolerance_deg": 0.05},
    {"mode": "external", "tolerance_mm": 0.5, "tolerance_deg": 0.05},
]


@pytest.mark.parametrize("body", RUN_BODIES)
def test_run_body_schema_says_exactly_one_of_stations_or_poses(doc: dict[str, Any],
                                                               body: dict[str, Any]) -> None:
    """The document accepts exactly the bodies the service accepts (``RunCreate``)."""
    assert body_schema(doc, "RunCreate").is_valid(body) == _accepts(RunCreate, body)
    assert len(doc["components"]["schemas"]["RunCreate"]["oneOf"]) == 4


def test_docs_show_named_shapes_and_valid_sample_bodies(doc: dict[str, Any]) -> None:
    """Issue 19: ReDoc named every shape of the run body "object" and showed a sample body
    mixing them, which the service refuses."""
    titles = [branch.get("title") for branch in doc["components"]["schemas"]["RunCreate"]["oneOf"]]
    assert None not in titles and len(set(titles)) == len(titles)
    examples = doc["paths"]["/runs"]["post"]["requestBody"]["content"]["application/json"][
        "examples"]
    assert len(examples) == 4
    for example in examples.values():
        assert _accepts(RunCreate, example["value"]), example
        assert body_schema(doc, "RunCreate").is_valid(example["value"])


@pytest.mark.parametrize("body", [{}, {"stations": 3}, {"poses": [[0.1] * 6]},
                                  {"stations": 3, "poses": [[0.1] * 6]},
                                  {"stations": 3, "poses": None}])
def test_check_body_schema_says_not_both(doc: dict[str, Any], body: dict[str, Any]) -> None:
    assert body_schema(doc, "CheckCreate").is_valid(body) == _accepts(CheckCreate, body)


def test_both_stations_and_poses_is_the_json_422(client: TestClient) -> None:
    r = client.post("/runs", json={"stations": 5, "poses": [[0.1] * 6]}, headers=AUTH)
    assert r.status_code == 422
    body = r.json()
    assert ErrorBody.model_validate(body).code == "invalid_request"
    assert "exactly one of 'stations'" in body["detail"]


def test_method_not_allowed_names_every_method_of_the_path(client: TestClient) -> None:
    r = client.request("TRACE", "/calibrations/abc", headers=AUTH)
    assert r.status_code == 405 and r.json()["code"] == "method_not_allowed"
    assert r.headers["allow"] == "GET, HEAD"
    r = client.request("PUT", "/runs/abc/calibrations", headers=AUTH)
    assert r.headers["allow"] == "GET, HEAD, POST"


def test_an_optional_body_that_is_not_utf8_is_the_json_422(client: TestClient) -> None:
    r = client.post("/calibrations/abc/checks", content=b'{"stations": "\xc3\x28"}',
                    headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 422
    assert r.json()["code"] == "invalid_request" and r.json()["detail"] == "body: not valid JSON"


@pytest.mark.parametrize("url", ["/calibrations?offset=9223372036854775808",
                                 "/runs/abc/stations/9223372036854775808"])
def test_numbers_beyond_any_row_are_422_not_500(client: TestClient, url: str) -> None:
    r = client.get(url, headers=AUTH)
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"


@pytest.mark.parametrize("body", [{"poses": [[False, 0, 0, 0, 0, 0]]}, {"stations": True},
                                  {"stations": "5"}])
def test_json_types_are_as_documented(client: TestClient, body: dict[str, Any]) -> None:
    r = client.post("/runs", json=body, headers=AUTH)
    assert r.status_code == 422 and r.json()["code"] == "invalid_request"


def test_a_refusal_for_storage_is_documented(doc: dict[str, Any]) -> None:
    """The requests that start work answer 503 ``storage_unavailable`` or ``disk_full`` while
    the data directory takes no writes (issue 22, row 5); the document said of every 503
    only that the database was not answering."""
    for path in ("/runs", "/runs/{run_id}/calibrations", "/calibrations/{cal_id}/activate",
                 "/calibrations/{cal_id}/checks", "/calibrations/{cal_id}/validations"):
        text = doc["paths"][path]["post"]["responses"]["503"]["description"]
        assert "storage_unavailable" in text and "disk_full" in text, (path, text)
