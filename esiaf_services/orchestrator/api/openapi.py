"""What FastAPI does not document by itself, written into the OpenAPI document: the token (a
bearer token, or ``?token=``) and its 401 on every operation but the open ones (``auth.py``), the
413 of request bodies over ``max_body_bytes`` (``limits.py``), the 400 of a body that cannot be
parsed, and the two shapes of a 422: FastAPI's list of validation errors, or one sentence for a
rule JSON Schema cannot state (``start_ns`` after ``end_ns``, a fusion that fuses its anchor).
schemathesis checks every answer against this document (tests/test_openapi_fuzz.py)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from .auth import is_open
from .models import Problem

SCHEMES = {
    "bearer": {"type": "http", "scheme": "bearer",
               "description": "the token (setting token, ESIAF_TOKEN or ESIAF_TOKEN_FILE; "
                              "esiaf run makes one per run)"},
    "query": {"type": "apiKey", "in": "query", "name": "token", "description": "the token, for browsers"},
}


def _problem(description: str) -> dict[str, Any]:
    return {"description": description,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Problem"}}}}


def _document(schema: dict[str, Any]) -> None:
    components = schema.setdefault("components", {})
    components.setdefault("schemas", {}).setdefault("Problem", Problem.model_json_schema())
    components["securitySchemes"] = SCHEMES
    for path, operations in schema.get("paths", {}).items():
        for method, operation in operations.items():
            responses = operation.setdefault("responses", {})
            if "requestBody" in operation:
                responses.setdefault("400", _problem("the body cannot be parsed (e.g. not UTF-8)"))
                responses.setdefault("413", _problem("the request body is over max_body_bytes"))
            if "422" in responses:  # FastAPI's validation errors, and this API's own rules in a sentence
                responses["422"]["content"] = {"application/json": {"schema": {"anyOf": [
                    {"$ref": "#/components/schemas/HTTPValidationError"},
                    {"$ref": "#/components/schemas/Problem"}]}}}
            if is_open(method.upper(), path):
                operation["security"] = []
                continue
            operation["security"] = [{"bearer": []}, {"query": []}]
            responses.setdefault("401", _problem("a token is configured and this request has none, "
                                                 "or a wrong one"))


def documented(app: FastAPI) -> Callable[[], dict[str, Any]]:
    """``app.openapi`` with the token and the body limit documented."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        schema = generate()  # FastAPI keeps it, and makes it again only if the routes change
        if "securitySchemes" not in schema.get("components", {}):
            _document(schema)
        return schema

    return openapi
