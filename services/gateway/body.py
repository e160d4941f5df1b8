"""Request bodies in JSON (validated by a pydantic model) or in the msgpack wire format.

`Content-Type: application/x-msgpack` bodies are decoded with the scanflow.wire message class;
anything else but JSON is refused with 415. The body size cap is enforced earlier (limits.py).
"""

from __future__ import annotations

from typing import Any, TypeVar

from fastapi import HTTPException, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from scanflow.wire import DecodeError, Message

from services.gateway.deps import KEY_ANSWERS

MSGPACK = "application/x-msgpack"
JSON = "application/json"
M = TypeVar("M", bound=BaseModel)
W = TypeVar("W", bound=Message)
# The answers of every endpoint that takes a body behind the API key (OpenAPI `responses`).
BODY_ANSWERS: dict[int | str, dict[str, Any]] = {
    **KEY_ANSWERS,
    413: {"description": "body over max_body_bytes"},
    415: {"description": "body neither JSON nor msgpack"},
    422: {"description": "invalid body; the message names the field"},
}


def content_type(request: Request) -> str:
    """The request's media type (Content-Type without parameters, lowercased); JSON when absent."""
    return request.headers.get("content-type", JSON).split(";", 1)[0].strip().lower()


async def read_body(request: Request, model: type[M], wire: type[W]) -> M | W:
    """The body as a validated `model` (JSON) or a decoded `wire` message (msgpack)."""
    kind = content_type(request)
    raw = await request.body()
    if kind == MSGPACK:
        try:
            return wire.decode(raw)
        except DecodeError as exc:
            raise HTTPException(422, f"body ({wire.TYPE} message): {exc}") from exc
    if kind != JSON:
        raise HTTPException(415, f"Content-Type must be {JSON} or {MSGPACK}, got {kind!r}")
    try:
        return model.model_validate_json(raw)
    except ValidationError as exc:
        errors = [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False)]
        raise RequestValidationError(errors) from exc


def invalid(loc: tuple[str | int, ...], message: str) -> RequestValidationError:
    """A 422 in FastAPI's own format for a check pydantic could not express."""
    return RequestValidationError([{"loc": loc, "msg": message, "type": "value_error"}])


def body_doc(model: type[BaseModel], wire: type[Message], summary: str) -> dict[str, Any]:
    """OpenAPI `requestBody` listing both encodings (schema registered by app.openapi)."""
    return {
        "requestBody": {
            "required": True,
            "description": summary,
            "content": {
                JSON: {"schema": {"$ref": f"#/components/schemas/{model.__name__}"}},
                MSGPACK: {
                    "schema": {
                        "type": "string",
                        "format": "binary",
                        "description": f"a scanflow.wire {wire.__name__} ({wire.TYPE!r})",
                    }
                },
            },
        }
    }
