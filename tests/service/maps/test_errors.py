"""The map domain knows no HTTP, and every one of its errors has its problem in the one table
(docs/design/service.md §2)."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from service.errors import DOMAIN_PROBLEMS, TITLES, domain_problem
from service.maps import errors

MAPS = Path(errors.__file__).parent
DOMAIN_ERRORS = [c for _, c in inspect.getmembers(errors, inspect.isclass)
                 if issubclass(c, errors.MapError) and c is not errors.MapError]


def test_nothing_under_service_maps_imports_http() -> None:
    for path in sorted(MAPS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                assert not name.startswith(("fastapi", "starlette", "service.errors", "service.routes")), \
                    (path.name, name)


@pytest.mark.parametrize("cls", DOMAIN_ERRORS, ids=lambda c: c.__name__)
def test_every_domain_error_has_its_problem(cls) -> None:
    assert cls in DOMAIN_PROBLEMS
    assert DOMAIN_PROBLEMS[cls].slug in TITLES


@pytest.mark.parametrize(("exc", "status", "slug", "members", "headers"), [
    (errors.MapNotFound("lab"), 404, "map-not-found", {"map_id": "lab"}, {}),
    (errors.MapUnavailable("lab", "failed", "database-corrupt"), 503, "map-unavailable",
     {"state": "failed", "state_reason": "database-corrupt"}, {}),
    (errors.MapFull("lab", 7), 409, "map-full", {"max_observations": 7}, {}),
    (errors.Overloaded(3), 503, "overloaded", {"retry_after": 1}, {"Retry-After": "1"}),
    (errors.InsufficientStorage("full"), 507, "insufficient-storage", {}, {}),
], ids=lambda v: v if isinstance(v, str) else None)
def test_the_table_gives_status_slug_members_and_headers(exc, status, slug, members, headers) -> None:
    p = domain_problem(exc)
    assert (p.status, p.slug, p.members, p.headers, p.detail) == (status, slug, members, headers, str(exc))


def test_the_data_directory_is_cut_from_the_detail(tmp_path) -> None:
    p = domain_problem(errors.InsufficientStorage(f"cannot write {tmp_path}/maps/lab/x"), tmp_path)
    assert p.detail == "cannot write maps/lab/x"


def test_a_failed_maps_503_says_what_an_operator_does_about_its_reason() -> None:
    corrupt = domain_problem(errors.MapUnavailable("lab", "failed", "database-corrupt")).detail
    assert corrupt.startswith("map 'lab' is failed (database-corrupt): ")
    assert "/v1/maps/lab/snapshots/" in corrupt and "`cortexloc import`" in corrupt and "DELETE" in corrupt
    unopenable = domain_problem(errors.MapUnavailable("lab", "failed", "unopenable")).detail
    assert "maps/lab/" in unopenable and "not" in unopenable and "damaged" in unopenable
    plain = domain_problem(errors.MapUnavailable("lab", "recovering", None)).detail
    assert plain == "map 'lab' is recovering"
