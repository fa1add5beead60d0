"""Fixtures the PostgreSQL store's tests share: an embedded PostgreSQL per test module, on
loopback, stopped after the module, and a fresh database in it per test."""

from __future__ import annotations

import hashlib

import psycopg
import pytest
from psycopg.conninfo import make_conninfo

from renderfarm.infra.embedded_db import EmbeddedPostgres


@pytest.fixture(scope="module")
def postgres(tmp_path_factory):
    """The server's URL (database `postgres`); the cluster is stopped after the module."""
    db = EmbeddedPostgres(tmp_path_factory.mktemp("pg"))
    url = db.start()
    try:
        yield url
    finally:
        db.stop()
    assert not (db.pgdata / "postmaster.pid").exists(), "the test's PostgreSQL still runs"


@pytest.fixture()
def db_url(postgres, request):
    """A fresh, empty database for one test; dropped after it."""
    name = "t_" + hashlib.sha256(request.node.nodeid.encode()).hexdigest()[:16]
    with psycopg.connect(postgres, autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        conn.execute(f'CREATE DATABASE "{name}"')
    yield make_conninfo(postgres, dbname=name)
    with psycopg.connect(postgres, autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
