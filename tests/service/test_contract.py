"""Schemathesis against the OpenAPI, in process, fresh data directory, bounded examples: no 5xx,
every 4xx is problem+json, and every body matches the schema /openapi.json declares for its status
(docs/design/service.md §10.2)."""

from __future__ import annotations

import contextlib

import pytest

schemathesis = pytest.importorskip("schemathesis")
from fastapi.testclient import TestClient  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from schemathesis.specs.openapi.checks import response_schema_conformance  # noqa: E402

from service.errors import PROBLEM_MEDIA_TYPE  # noqa: E402
from tests.service.helpers import make_app  # noqa: E402

try:  # schemathesis runs the app's lifespan itself (once per app, for the process)
    from schemathesis.python.asgi import shutdown_lifespans
except ImportError:  # an older one does not: the test runs it
    shutdown_lifespans = None


def test_every_operation_without_server_errors(tmp_path):
    app = make_app(tmp_path / "data")
    failures: list[str] = []
    calls: list[int] = []
    # One lifespan (encoder, maps): a second would open the data directory again, which its lock refuses.
    with contextlib.ExitStack() as stack:
        if shutdown_lifespans is None:
            stack.enter_context(TestClient(app))
        else:
            stack.callback(shutdown_lifespans)  # the maps closed, the directory's lock let go
        schema = schemathesis.openapi.from_asgi("/openapi.json", app)
        operations = [r.ok() for r in schema.get_all_operations()]
        assert len(operations) >= 10
        for op in operations:
            @given(case=op.as_strategy())
            # derandomized: CI sees the same examples every run, so a red run is reproducible, not luck
            @settings(max_examples=10, deadline=None, suppress_health_check=list(HealthCheck), database=None,
                      derandomize=True)
            def check(case) -> None:
                response = case.call()
                calls.append(response.status_code)
                where = f"{case.method} {case.formatted_path}: {response.status_code}"
                ctype = response.headers.get("content-type", "")
                ctype = ctype[0] if isinstance(ctype, list) else ctype  # schemathesis lists header values
                if response.status_code >= 500:
                    failures.append(where)
                elif response.status_code >= 400 and not ctype.startswith(PROBLEM_MEDIA_TYPE):
                    failures.append(f"{where} is not problem+json")
                try:
                    case.validate_response(response, checks=[response_schema_conformance])
                except AssertionError as e:  # schemathesis' failures are AssertionErrors (grouped)
                    failures.append(f"{where} does not match its schema: {str(e)[:300]}")

            check()
    assert not failures, failures[:10]
    assert len(calls) >= 5 * len(operations)  # the generator really exercised every operation
