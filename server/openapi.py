"""The OpenAPI document as a contract that clients are generated from.

FastAPI builds the document from the routes; :func:`install` post-processes it once per app with what FastAPI
cannot infer:

- Every error response (4xx, 5xx) is the RFC 9457 :class:`~server.errors.Problem` schema served as
  ``application/problem+json``; FastAPI's ``HTTPValidationError`` is gone from the document.
- Errors that follow from an operation's shape are documented on every operation of that shape
  (:data:`SHAPE_ERRORS`): 401 and 429 where the bearer scheme applies, 404 where the path names a resource, 422
  where a parameter or the body is validated, 400/413/415 where a request body passes the body-limit middleware.
  Errors that follow from what a route does (403 for a role, 409 for a state, a 422 with a meaning of its own, 503)
  are declared at the route with ``responses={code: {"description": ...}}`` and get the same schema here.
- Every request body has a description; a body a route parses itself (``openapi_extra``) becomes a named component;
  the models' examples keep their nulls.

Operation ids are the route functions' names in camelCase (:func:`operation_id`) unless a route names its own.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute
from pydantic import BaseModel

from server.errors import PROBLEM_JSON, Problem

OPERATION_ID_RULE = re.compile(r"^[a-z][a-z0-9]*(?:[A-Z][a-z0-9]*)*$")
HTTP_METHODS = ("get", "put", "post", "delete", "patch", "options", "head", "trace")
PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}
_FASTAPI_VALIDATION_SCHEMAS = ("HTTPValidationError", "ValidationError")
_FASTAPI_VALIDATION_DESCRIPTION = "Validation Error"

Shape = Callable[[dict[str, Any]], bool]


def _has_bearer(op: dict[str, Any]) -> bool:
    return any("bearerAuth" in requirement for requirement in op.get("security", []))


def _has_path_parameter(op: dict[str, Any]) -> bool:
    return any(p.get("in") == "path" for p in op.get("parameters", []))


def _has_input(op: dict[str, Any]) -> bool:
    return bool(op.get("parameters")) or "requestBody" in op


def _has_body(op: dict[str, Any]) -> bool:
    return "requestBody" in op


RETRY_AFTER = {"Retry-After": {"description": "Seconds to wait before the next request",
                               "schema": {"type": "integer"}}}
WWW_AUTHENTICATE = {"WWW-Authenticate": {"description": "`Bearer realm=\"gaitmon\"`", "schema": {"type": "string"}}}

# status -> (which operations answer it, description, response headers)
SHAPE_ERRORS: dict[int, tuple[Shape, str, dict[str, Any]]] = {
    400: (_has_body, "The body is not valid gzip, is truncated, or its Content-Length is not an integer", {}),
    401: (_has_bearer, "Missing, malformed, unknown or revoked bearer token", WWW_AUTHENTICATE),
    404: (_has_path_parameter, "No such resource, or it belongs to someone else (the caller cannot tell which)", {}),
    413: (_has_body, "The body exceeds the size limit (measured after gzip decompression)", {}),
    415: (_has_body, "A Content-Encoding other than gzip or identity", {}),
    422: (_has_input, "A parameter or the body is invalid; `errors` names each invalid field", {}),
    429: (_has_bearer, "Too many requests from this token or address; retry after `Retry-After` seconds",
          RETRY_AFTER),
}


def operation_id(route: APIRoute) -> str:
    """The operation id of a route that names none: its function's name in camelCase (``upload_batch`` ->
    ``uploadBatch``)."""
    head, *rest = route.name.split("_")
    return head + "".join(part[:1].upper() + part[1:] for part in rest)


def operations(spec: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """Every operation of the document as (method, path, operation object)."""
    return [(method, path, op) for path, item in spec.get("paths", {}).items()
            for method, op in item.items() if method in HTTP_METHODS]


def _problem_response(description: str, headers: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"description": description, "content": {PROBLEM_JSON: {"schema": dict(PROBLEM_REF)}}}
    if headers:
        out["headers"] = headers
    return out


def _document_errors(op: dict[str, Any]) -> None:
    responses: dict[str, Any] = op.setdefault("responses", {})
    for status, (applies, description, headers) in SHAPE_ERRORS.items():
        if applies(op):
            responses.setdefault(str(status), {})
            declared = responses[str(status)].get("description")
            if declared in (None, "", _FASTAPI_VALIDATION_DESCRIPTION):
                responses[str(status)]["description"] = description
            responses[str(status)].setdefault("headers", headers)
    for code, response in list(responses.items()):
        if code[:1] in ("4", "5"):
            responses[code] = _problem_response(response.get("description") or _description_of(int(code)),
                                                response.get("headers") or {})
    op["responses"] = dict(sorted(responses.items()))


def _description_of(status: int) -> str:
    """The shape rule's description of a status, else its HTTP reason phrase."""
    if status in SHAPE_ERRORS:
        return SHAPE_ERRORS[status][1]
    return HTTPStatus(status).phrase


def _rewrite_refs(node: Any, old: str, new: str) -> Any:
    if isinstance(node, dict):
        return {k: (v.replace(old, new, 1) if k == "$ref" and isinstance(v, str) and v.startswith(old)
                    else _rewrite_refs(v, old, new)) for k, v in node.items()}
    if isinstance(node, list):
        return [_rewrite_refs(v, old, new) for v in node]
    return node


def _named_body(op: dict[str, Any], schemas: dict[str, Any]) -> None:
    """An inline request body schema with a title (a model a route parses itself) becomes a component."""
    for media in op.get("requestBody", {}).get("content", {}).values():
        schema = media.get("schema") or {}
        title = schema.get("title")
        if schema.get("type") != "object" or not title:
            continue
        schema = _rewrite_refs(schema, "#/$defs/", "#/components/schemas/")
        for name, sub in schema.pop("$defs", {}).items():
            schemas.setdefault(name, sub)
        schemas.setdefault(title, schema)
        media["schema"] = {"$ref": f"#/components/schemas/{title}"}


def _resolve(schema: dict[str, Any], schemas: dict[str, Any]) -> dict[str, Any]:
    ref = schema.get("$ref") or next((s.get("$ref") for s in schema.get("anyOf", []) if "$ref" in s), None)
    return schemas.get(ref.rsplit("/", 1)[-1], {}) if ref else schema


def _describe_body(op: dict[str, Any], schemas: dict[str, Any]) -> None:
    body = op.get("requestBody")
    if body is None or body.get("description"):
        return
    for media in body.get("content", {}).values():
        description = _resolve(media.get("schema") or {}, schemas).get("description")
        if description:
            body["description"] = description
            return


def _drop_unused_validation_schemas(spec: dict[str, Any]) -> None:
    schemas = spec.get("components", {}).get("schemas", {})
    text = repr(spec.get("paths", {}))
    for name in _FASTAPI_VALIDATION_SCHEMAS:
        if f"#/components/schemas/{name}'" not in text:
            schemas.pop(name, None)


def _declared_examples() -> dict[str, list[Any]]:
    """The ``examples`` of every model of the service, by class name (a name two models share is left out)."""
    found: dict[str, list[Any]] = {}
    ambiguous: set[str] = set()
    stack = list(BaseModel.__subclasses__())
    while stack:
        model = stack.pop()
        stack.extend(model.__subclasses__())
        extra = model.model_config.get("json_schema_extra")
        if not model.__module__.startswith("server.") or not isinstance(extra, dict) or "examples" not in extra:
            continue
        if model.__name__ in found and found[model.__name__] is not extra["examples"]:
            ambiguous.add(model.__name__)
        found[model.__name__] = extra["examples"]
    return {name: examples for name, examples in found.items() if name not in ambiguous}


def _restore_examples(schemas: dict[str, Any]) -> None:
    # FastAPI encodes the document with exclude_none, which drops every null out of the examples too: an example
    # of a required nullable field would lose the field and no longer be valid for its own schema.
    for name, examples in _declared_examples().items():
        if name in schemas:
            schemas[name]["examples"] = examples


def _check_operation_ids(spec: dict[str, Any]) -> None:
    ids = [op.get("operationId", "") for _, _, op in operations(spec)]
    duplicates = sorted({i for i in ids if ids.count(i) > 1})
    bad = sorted(i for i in ids if not OPERATION_ID_RULE.match(i))
    if duplicates or bad:
        raise ValueError(f"operation ids must be unique camelCase: duplicates {duplicates}, malformed {bad}")


def contract(spec: dict[str, Any]) -> dict[str, Any]:
    """Post-process a FastAPI document in place (see the module docstring) and return it."""
    components = spec.setdefault("components", {})
    schemas = components.setdefault("schemas", {})
    problem = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    for name, sub in problem.pop("$defs", {}).items():
        schemas[name] = sub
    schemas["Problem"] = problem
    for _, _, op in operations(spec):
        _named_body(op, schemas)
        _describe_body(op, schemas)
        _document_errors(op)
    _drop_unused_validation_schemas(spec)
    _restore_examples(schemas)
    components["schemas"] = dict(sorted(schemas.items()))
    _check_operation_ids(spec)
    return spec


def install(app: FastAPI) -> None:
    """Serve the post-processed document at ``/openapi.json`` (built once, on first request)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = contract(build())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
