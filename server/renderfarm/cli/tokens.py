"""`renderfarm token create|ls|revoke`: API tokens, managed on the database directly.

The commands take the server's own settings (RENDERFARM_DATABASE_URL, or RENDERFARM_DATA_DIR for
the embedded PostgreSQL, which they attach to while the server runs), so the first admin token
can be made before a server is exposed beyond loopback. A running server notices a new or
revoked token within auth.CACHE_S seconds.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from ..app import auth
from ..infra.config import Settings
from ..infra.embedded_db import EmbeddedPostgres
from ..infra.store import Store, TokenRow

T = TypeVar("T")


async def _with_store(settings: Settings, work: Callable[[Store], Awaitable[T]]) -> T:
    embedded = None
    url = settings.database_url
    if not url:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        embedded = EmbeddedPostgres(settings.data_dir)
        url = await asyncio.to_thread(embedded.start)
    store = Store(url, min_size=1, max_size=2)
    try:
        await store.open()
        return await work(store)
    finally:
        await store.close()
        if embedded is not None:
            await asyncio.to_thread(embedded.stop)


def describe(row: TokenRow) -> dict[str, Any]:
    return {
        "id": row.id,
        "name": row.name,
        "admin": row.admin,
        "created_unix_s": row.created_at.timestamp(),
        "revoked_unix_s": row.revoked_at.timestamp() if row.revoked_at else None,
    }


def create(settings: Settings, name: str, admin: bool) -> tuple[dict[str, Any], str]:
    """A new token: (its description, the token, which is never shown again)."""

    async def work(store: Store):
        return await auth.create_token(store, name, admin)

    row, token = asyncio.run(_with_store(settings, work))
    return describe(row), token


def list_all(settings: Settings) -> list[dict[str, Any]]:
    async def work(store: Store):
        return await store.list_tokens()

    return [describe(r) for r in asyncio.run(_with_store(settings, work))]


def revoke(settings: Settings, token_id: str) -> dict[str, Any] | None:
    async def work(store: Store):
        return await store.revoke_token(token_id)

    row = asyncio.run(_with_store(settings, work))
    return describe(row) if row else None
