"""The OpenAPI document against the service, property-based (schemathesis): every operation
with generated valid and invalid requests, the mock devices and SQLite; every check passes
(no 500, only documented statuses, bodies and headers as documented, invalid requests
refused, valid ones accepted).

Bounded and deterministic: few examples per operation, ``derandomize`` (the same examples
on every run), no deadline (a loaded machine is slow, not wrong).
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.config import SchemathesisConfig
from schemathesis.python.asgi import shutdown_lifespans

from service.app import create_app
from tests.support.service import AUTH
from tests.support.service import settings as service_settings

#: Generated requests per operation and phase; the document has about 30 operations.
MAX_EXAMPLES = 5


#: The service under test: the mock devices, SQLite in a directory of its own. Building the app
#: runs nothing; its lifespan starts with the first request and ends in ``cleanup``.
DATA_DIR = Path(tempfile.mkdtemp(prefix="cellcal-schemathesis-"))
# Removed when the process ends: also where this file is only collected (``-m slow``, the other
# xdist worker) and ``cleanup`` never runs.
atexit.register(shutil.rmtree, DATA_DIR, ignore_errors=True)
APP = create_app(service_settings(DATA_DIR))
#: Schema-valid requests these operations answer 422 on purpose, as documented: what makes them
#: valid is not a JSON schema (poses inside the configured workspace, rotation vectors of at
#: most π rad, a form part that is a PNG or JPEG file).
SEMANTIC_422 = [("POST", "/runs"), ("POST", "/runs/{run_id}/stations"),
                ("POST", "/calibrations/{cal_id}/checks"),
                ("POST", "/calibrations/{cal_id}/validations")]
#: Unknown query parameters are ignored, as HTTP services commonly do (proxies and browsers add
#: some): no generated request tests their refusal.
CONFIG = SchemathesisConfig.from_dict({"generation": {"allow-extra-parameters": False},
                                       "operations": [
    {"include-method": method, "include-path": path, "checks": {"positive_data_acceptance": {
        "expected-statuses": ["2xx", "401", "404", "409", "422", "429"]}}}
    for method, path in SEMANTIC_422]})
schema = schemathesis.openapi.from_dict(APP.openapi(), config=CONFIG)
schema.config.update(base_url="http://127.0.0.1")
schema.app = APP


@pytest.fixture(scope="module", autouse=True)
def cleanup() -> Iterator[None]:
    yield
    shutdown_lifespans()  # the app's lifespan: devices, capture threads, worker processes


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
def test_every_operation_answers_as_documented(case: schemathesis.Case) -> None:
    case.call_and_validate(headers=AUTH)
