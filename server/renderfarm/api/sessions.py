"""The REST API's token of a request: the Authorization header, else the dashboard's session
cookie (POST /api/v1/session sets it, DELETE clears it: api/rest.py)."""

from __future__ import annotations

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
