"""The OpenAPI document against the service, property-based (schemathesis): every operation
with generated valid and invalid requests, the mock devices and SQLite; every check passes
(no 500, only documented statuses, bodies and headers as documented, invalid requests
refused, valid ones accepted).

Bounded and deterministic: few examples per operation, ``derandomize`` (the same examples
on every run), no deadline (a loaded machine is slow, not wrong).

The schema is lazy (``schemathesis.pytest.from_fixture``): the app, its document and the
cases of every operation are built when the test runs, in the one process that runs it, and
each operation is reported as a subtest. Built at collection, as ``schema.parametrize()`` on a
module-level schema does, they cost every process that collects this file 2-3 CPU s (each
pytest-xdist worker of ``make test``, and ``make test-slow``, which only deselects it; the fast
suite's collection took 9.7 CPU s, now 7.6), mostly schemathesis's coverage phase enumerating
each operation's boundary and negative cases. The cases are the same (1,203 requests).
"""

from __future__ import annotations

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

#: Schema-valid requests these operations answer 422 on purpose, as documented: what makes them
#: valid is not a JSON schema (poses inside the configured workspace, rotation vectors of at
#: most π rad, a form part that is a PNG or JPEG file).
SEMANTIC_422 = [("POST", "/runs"), ("POST", "/runs/{run_id}/stations"),
                ("POST", "/calibrations/{cal_id}/checks"),
                ("POST", "/calibrations/{cal_id}/validations")]
#: Unknown query parameters are ignored, as HTTP services commonly do (proxies and browsers add
#: some): no generated request tests their refusal.
CONFIG = {"generation": {"allow-extra-parameters": False},
          "operations": [
    {"include-method": method, "include-path": path, "checks": {"positive_data_acceptance": {
        "expected-statuses": ["2xx", "401", "404", "409", "422", "429"]}}}
    for method, path in SEMANTIC_422]}


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[schemathesis.BaseSchema]:
    """The service under test (mock devices, SQLite in a directory of its own) and its
    document. Building the app runs nothing: its lifespan starts with the first request and
    ends with ``shutdown_lifespans`` (devices, capture threads, worker processes)."""
    data_dir: Path = tmp_path_factory.mktemp("schemathesis")
    app = create_app(service_settings(data_dir))
    schema = schemathesis.openapi.from_dict(app.openapi(),
                                            config=SchemathesisConfig.from_dict(CONFIG))
    schema.config.update(base_url="http://127.0.0.1")
    schema.app = app
    try:
        yield schema
    finally:
        shutdown_lifespans()


lazy_schema = schemathesis.pytest.from_fixture("api_schema")


@pytest.fixture(autouse=True)
def _node_id_for_subtests(request: pytest.FixtureRequest) -> None:
    """schemathesis 4.32 names each operation's subtest by rewriting the test item's
    ``_nodeid``, which pytest 9.2 no longer has (its node id is kept elsewhere): give it one."""
    request.node._nodeid = request.node.nodeid


@pytest.mark.timeout(900)  # the whole document in one test: a hang guard, not a speed target
@lazy_schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
def test_every_operation_answers_as_documented(case: schemathesis.Case) -> None:
    case.call_and_validate(headers=AUTH)
