"""The OpenAPI document as served: FastAPI's, with its validation errors documented as what they are
here, 400 problem+json (docs/design/service.md §2)."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from service.errors import problem_responses

__all__ = ["openapi_with_problems"]


def openapi_with_problems(app: FastAPI) -> Callable[[], dict[str, Any]]:
    """FastAPI documents validation errors as 422 HTTPValidationError; they are 400 problem+json here."""
    original = app.openapi
    invalid = problem_responses(400)[400]

    def openapi() -> dict[str, Any]:
        schema = original()
        for path_item in schema.get("paths", {}).values():
            for op in path_item.values():
                responses = op.get("responses") if isinstance(op, dict) else None
                if not responses or "422" not in responses:
                    continue
                if "HTTPValidationError" in json.dumps(responses["422"]):
                    del responses["422"]
                    responses.setdefault("400", invalid)
        components = schema.get("components", {}).get("schemas", {})
        for name in ("HTTPValidationError", "ValidationError"):
            if name in components:
                rest = {k: v for k, v in components.items() if k != name}
                if f"#/components/schemas/{name}" not in json.dumps({"paths": schema["paths"], "c": rest}):
                    del components[name]
        return schema

    return openapi
