"""How the REST API answers each exception type (errors.py): JSON {"detail", "field"} with the
status code the module docstring of rest.py lists, and the same shape for FastAPI's and
Starlette's own answers and for unexpected failures (500)."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from ..errors import AuthError, Conflict, Forbidden, NotFound, SceneError, SettingsError, TooLarge
from ..infra.store import DatabaseUnavailable
from .models import error_response


def add_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(AuthError)
    async def _auth_error(_: Request, e: AuthError):
        return error_response(401, "authorization", e.message, {"WWW-Authenticate": "Bearer"})

    @app.exception_handler(Forbidden)
    async def _forbidden(_: Request, e: Forbidden):
        return error_response(403, "job_id", e.message)

    @app.exception_handler(SettingsError)
    async def _settings_error(_: Request, e: SettingsError):
        return error_response(400, e.field, e.message)

    @app.exception_handler(SceneError)
    async def _scene_error(_: Request, e: SceneError):
        return error_response(400, e.field, str(e))

    @app.exception_handler(TooLarge)
    async def _too_large(_: Request, e: TooLarge):
        return error_response(413, e.field, e.message)

    @app.exception_handler(Conflict)
    async def _conflict(_: Request, e: Conflict):
        return error_response(409, "", e.message)

    @app.exception_handler(NotFound)
    async def _not_found(_: Request, e: NotFound):
        return error_response(404, e.field, e.message)

    @app.exception_handler(DatabaseUnavailable)
    async def _unavailable(_: Request, e: DatabaseUnavailable):
        return error_response(
            e.status, "database", e.message, {"Retry-After": str(e.retry_after_s)}
        )

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, e: RequestValidationError):
        first = e.errors()[0] if e.errors() else {}
        loc = first.get("loc", ())
        if first.get("type") == "json_invalid":  # its loc is the character offset, not a field
            return error_response(400, "body", "request body is not valid JSON")
        where = [str(p) for p in loc if p not in ("query", "path", "body")]
        name = ".".join(where) or ("body" if loc[:1] == ("body",) else "")
        return error_response(400, name, f"{name or 'request'}: {first.get('msg', 'invalid')}")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, e: StarletteHTTPException):
        # Raised by FastAPI and Starlette themselves: 404 for an unknown path, 405 for a wrong
        # method, and 400 for a body they could not parse (JSON nested deeper than the parser
        # goes, broken multipart).
        if e.status_code != 400:
            return error_response(e.status_code, "", str(e.detail), e.headers)
        detail = str(e.detail)
        if isinstance(e.__cause__, RecursionError):
            detail = "request body is not valid JSON: nested too deeply"
        return error_response(400, "body", detail, e.headers)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, e: Exception):
        # A bug, not the client's fault; Starlette re-raises it after this answer, so the
        # traceback is still logged.
        return error_response(500, "", "internal server error")
