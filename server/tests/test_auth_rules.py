"""The rules of auth.py without a database: loopback detection, the exposure check, bearer
parsing, ownership."""

from __future__ import annotations

import asyncio

import pytest

from renderfarm.api.sessions import bearer
from renderfarm.app.auth import (
    LOCAL_USER,
    Authenticator,
    Caller,
    check_exposure,
    is_loopback,
    token_sha256,
)
from renderfarm.errors import AuthError


@pytest.mark.parametrize("host", ["127.0.0.1", "127.8.9.1", "::1", "[::1]", "localhost"])
def test_loopback_addresses(host):
    assert is_loopback(host)


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "10.1.2.3", "farm.example.org", ""])
def test_other_addresses(host):
    assert not is_loopback(host)


def test_exposure_needs_a_client_token_and_a_worker_token():
    assert check_exposure("127.0.0.1", "::1", 0, "") is None
    assert check_exposure("0.0.0.0", "127.0.0.1", 1, "w") is None
    both = check_exposure("0.0.0.0", "127.0.0.1", 0, "")
    assert "0.0.0.0" in both and "no API token" in both and "no worker token" in both
    assert "no worker token" not in check_exposure("127.0.0.1", "10.0.0.1", 0, "w")
    assert "no API token" not in check_exposure("10.0.0.1", "10.0.0.1", 2, "")


def test_bearer_header_parsing():
    assert bearer("Bearer abc") == bearer("bearer  abc ") == "abc"
    assert bearer(None) is bearer("") is bearer("Basic abc") is bearer("Bearer ") is None


def test_ownership():
    alice = Caller("alice", admin=False)
    assert alice.may_access("alice") and not alice.may_access("bob")
    assert Caller("root", admin=True).may_access("bob") and LOCAL_USER.may_access("anyone")


class FakeStore:
    def __init__(self, tokens):
        self.tokens = tokens
        self.lookups = 0

    async def live_token_count(self):
        return sum(1 for t in self.tokens.values() if t.revoked_at is None)

    async def token_by_hash(self, digest):
        self.lookups += 1
        return self.tokens.get(digest)


def test_auth_is_off_only_without_tokens_on_loopback():
    store = FakeStore({})
    assert asyncio.run(Authenticator(store, loopback_only=True).caller(None)) == LOCAL_USER
    with pytest.raises(AuthError):
        asyncio.run(Authenticator(store, loopback_only=False).caller(None))
    with pytest.raises(AuthError, match="no tokens"):
        asyncio.run(Authenticator(store, loopback_only=True).caller("rf_x"))


def test_tokens_are_looked_up_by_hash_and_cached():
    from datetime import UTC, datetime

    from renderfarm.infra.store import TokenRow

    row = TokenRow("id1", "alice", token_sha256("rf_a"), False, datetime.now(UTC), None)
    store = FakeStore({row.sha256: row})
    now = [0.0]
    auth = Authenticator(store, loopback_only=True, clock=lambda: now[0])

    async def twice():
        return [await auth.caller("rf_a"), await auth.caller("rf_a")]

    assert asyncio.run(twice()) == [Caller("alice", False)] * 2
    assert store.lookups == 1
    with pytest.raises(AuthError, match="required"):
        asyncio.run(auth.caller(None))
