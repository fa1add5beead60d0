"""The REST API's token of a request (the Authorization header, else the dashboard's session
cookie), gRPC's bearer metadata, and the routes that set and clear the cookie
(POST and DELETE /api/v1/session)."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response

from ..app.auth import Authenticator
from ..errors import AuthError
from .models import SessionIn, WhoAmI, error_responses

# The dashboard's session cookie (POST /api/v1/session): the API token itself, HttpOnly, so that
# EventSource and <img> requests, which cannot send an Authorization header, carry it.
SESSION_COOKIE = "renderfarm_token"


def request_token(authorization: str | None, cookie: str | None) -> str | None:
    """The token of a REST request: the Authorization header, else the session cookie."""
    if authorization:
        return bearer(authorization)
    return cookie.strip() if cookie and cookie.strip() else None


def bearer(header_value: str | None) -> str | None:
    """The token of an `Authorization: Bearer TOKEN` value, or None."""
    if not header_value:
        return None
    scheme, _, token = header_value.strip().partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


def add_session_routes(app: FastAPI, auth: Authenticator) -> None:
    """POST and DELETE /api/v1/session: the dashboard signs in and out."""

    @app.post(
        "/api/v1/session",
        summary="Sign in the dashboard: check a token and keep it in an HttpOnly session cookie",
        description=(
            f"On success sets the cookie `{SESSION_COOKIE}` (HttpOnly, SameSite=Strict, Secure "
            "over TLS), which then authorizes requests without an Authorization header."
        ),
        response_model=WhoAmI,
        responses=error_responses(),
    )
    async def sign_in(body: SessionIn, request: Request) -> JSONResponse:
        token = body.token.strip()
        if not token:
            raise AuthError("an API token is required")
        who = await auth.caller(token)  # AuthError: 401, and no cookie
        response = JSONResponse({"owner": who.owner, "admin": who.admin})
        response.set_cookie(
            SESSION_COOKIE,
            token,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
            path="/",
        )
        return response

    @app.delete(
        "/api/v1/session",
        status_code=204,
        summary="Sign out the dashboard: clear the session cookie",
        response_class=Response,
    )
    async def sign_out(request: Request) -> Response:
        response = Response(status_code=204)
        response.delete_cookie(
            SESSION_COOKIE,
            path="/",
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
        return response
