"""API tokens: who is calling, and may they touch this job.

Clients send `Authorization: Bearer TOKEN` (REST) or the metadata `authorization: Bearer TOKEN`
(gRPC). Tokens are random strings shown once when created (`renderfarm token create`); the
database keeps only their SHA-256. A job is owned by the name of the token that submitted it;
admin tokens may read, cancel and delete every job.

Auth is off only while no live token exists and the server listens on loopback (the single-user
local farm). As soon as one token exists, every API call needs one. A server on any other
address refuses to start without a client token and a worker token (`check_exposure`).
"""

from __future__ import annotations

import hashlib
import ipaddress
import logging
import secrets
import time
from dataclasses import dataclass
from typing import Any

import psycopg
from psycopg_pool import PoolTimeout

from ..errors import AuthError
from ..infra.store import Store, TokenRow

log = logging.getLogger(__name__)
DB_RETRY_S = 5.0  # while the database is away, ask it again this often

TOKEN_PREFIX = "rf_"
# How long a looked-up token (or the "no tokens exist" answer) is trusted before the database
# is asked again: a revoked token stops working within this many seconds.
CACHE_S = 2.0


@dataclass(frozen=True)
class Caller:
    """Who made a request. `owner` is what their jobs are stored under."""

    owner: str
    admin: bool

    def may_access(self, job_owner: str) -> bool:
        return self.admin or job_owner == self.owner


# The caller when auth is off: the farm's only user, who may do everything.
LOCAL_USER = Caller(owner="", admin=True)


def new_token() -> str:
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def token_sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def is_loopback(host: str) -> bool:
    if host in ("localhost", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_exposure(
    http_host: str, grpc_host: str, live_tokens: int, worker_token: str
) -> str | None:
    """Why the server must not start listening on these addresses, or None when it may."""
    exposed = [h for h in (http_host, grpc_host) if not is_loopback(h)]
    if not exposed:
        return None
    missing = []
    if live_tokens == 0:
        missing.append("no API token exists (create one: renderfarm token create NAME --admin)")
    if not worker_token:
        missing.append("no worker token is set (RENDERFARM_WORKER_TOKEN or --worker-token)")
    if not missing:
        return None
    return f"refusing to listen on {', '.join(sorted(set(exposed)))} (not loopback): " + "; ".join(
        missing
    )


class Authenticator:
    """Turns a presented token into a Caller, with a short cache in front of the database."""

    def __init__(self, store: Store, loopback_only: bool, clock=time.monotonic):
        self.store = store
        self.loopback_only = loopback_only
        self.clock = clock
        self._tokens: dict[str, tuple[float, TokenRow | None]] = {}
        self._live: tuple[float, int] | None = None
        self._db_down_until = 0.0  # after a failed lookup, use cached answers for a while

    @classmethod
    def for_settings(cls, store: Store, settings) -> Authenticator:
        """Auth may be off (no tokens) only when both APIs listen on loopback."""
        loopback = is_loopback(settings.http_host) and is_loopback(settings.grpc_host)
        return cls(store, loopback_only=loopback)

    def forget(self) -> None:
        """Drop cached answers (after creating or revoking a token in this process)."""
        self._tokens.clear()
        self._live = None

    async def _live_tokens(self) -> int:
        now = self.clock()
        stale = self._live is None or now - self._live[0] > CACHE_S
        if stale and (self._live is None or now >= self._db_down_until):
            try:
                self._live = (now, await self.store.live_token_count())
            except (psycopg.Error, PoolTimeout, OSError):
                if self._live is None:
                    raise  # nothing known yet: the caller gets 503
                # The database is away: the last answer stands until it is back (a token
                # revoked during the outage takes effect when the database returns).
                self._db_down_until = now + DB_RETRY_S
                log.warning("database unreachable; using the cached token state")
        return self._live[1]

    async def _lookup(self, token: str) -> TokenRow | None:
        digest = token_sha256(token)
        now = self.clock()
        cached = self._tokens.get(digest)
        stale = cached is None or now - cached[0] > CACHE_S
        if stale and (cached is None or now >= self._db_down_until):
            if len(self._tokens) > 10000:  # bounded: a flood of wrong tokens cannot grow it
                self._tokens.clear()
            try:
                cached = (now, await self.store.token_by_hash(digest))
            except (psycopg.Error, PoolTimeout, OSError):
                if cached is None:
                    raise
                self._db_down_until = now + DB_RETRY_S
                log.warning("database unreachable; using the cached token state")
            self._tokens[digest] = cached
        return cached[1]

    async def caller(self, token: str | None) -> Caller:
        """The caller presenting `token` (None: no token). Raises AuthError."""
        if token is None:
            if self.loopback_only and await self._live_tokens() == 0:
                return LOCAL_USER
            raise AuthError("an API token is required: send the header Authorization: Bearer TOKEN")
        row = await self._lookup(token)
        if row is None:
            if self.loopback_only and await self._live_tokens() == 0:
                raise AuthError("unknown API token (this server has no tokens; send none)")
            raise AuthError("unknown API token")
        if row.revoked_at is not None:
            raise AuthError(f"API token {row.id} ({row.name}) was revoked")
        return Caller(owner=row.name, admin=row.admin)


def check_caller(caller: Any) -> None:
    """Every job operation names its caller: there is no default identity to fall back on
    (one would grant the local admin's rights to a handler that forgot to pass it)."""
    if not isinstance(caller, Caller):
        raise TypeError(f"FarmService needs the caller (an auth.Caller), got {caller!r}")


async def ensure_configured_token(store: Store, token: str) -> None:
    """RENDERFARM_ADMIN_TOKEN: an admin token named "admin" with this secret exists."""
    if token:
        await store.ensure_token(secrets.token_hex(4), "admin", token_sha256(token), True)


async def create_token(store: Store, name: str, admin: bool) -> tuple[TokenRow, str]:
    """A new token: (its row, the token itself, which is shown once and never stored)."""
    name = name.strip()
    if not name or len(name) > 100:
        raise ValueError("a token name is 1 to 100 characters")
    live = {t.name for t in await store.list_tokens() if t.revoked_at is None}
    if name in live:
        raise ValueError(f"a live token named {name!r} exists; revoke it first or pick another")
    token = new_token()
    row = await store.create_token(secrets.token_hex(4), name, token_sha256(token), admin)
    return row, token


__all__ = [
    "LOCAL_USER",
    "Authenticator",
    "Caller",
    "check_caller",
    "check_exposure",
    "create_token",
    "is_loopback",
    "token_sha256",
]
