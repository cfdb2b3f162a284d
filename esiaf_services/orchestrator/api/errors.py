"""405 with the whole Allow header. Starlette answers a method that a path does not take from the
first route of the path alone, so a path served by two routes (GET and POST /components) said
``Allow: POST``; here every operation of the path in the OpenAPI document counts."""
from __future__ import annotations

import re

from fastapi import Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import Response
from starlette.exceptions import HTTPException


def _documented_methods(request: Request) -> set[str]:
    methods: set[str] = set()
    for template, operations in request.app.openapi().get("paths", {}).items():
        pattern = "".join("[^/]+" if part.startswith("{") else re.escape(part)
                          for part in re.split(r"(\{[^}]*\})", template))
        if re.fullmatch(pattern, request.url.path):
            methods.update(method.upper() for method in operations)
    return methods


async def with_allow_header(request: Request, exc: HTTPException) -> Response:
    if exc.status_code == 405 and (methods := _documented_methods(request)):
        exc.headers = {**(exc.headers or {}), "Allow": ", ".join(sorted(methods))}
    return await http_exception_handler(request, exc)
