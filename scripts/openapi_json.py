#!/usr/bin/env python3
"""Writes the REST API's OpenAPI document to web/openapi.json (`make openapi`), from which the
dashboard's TypeScript types are generated (openapi-typescript, `npm run api-types`).
server/tests/test_openapi_document.py fails while the file is stale."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from unittest.mock import MagicMock

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "server"))


def document() -> str:
    """The document as the server serves it at /openapi.json (routes and models only: no farm
    is started, the app's handlers are never called)."""
    from renderfarm.api.rest import create_app

    farm = MagicMock()
    farm.settings.http_host = farm.settings.grpc_host = "127.0.0.1"
    return json.dumps(create_app(farm, MagicMock()).openapi(), indent=1, sort_keys=True) + "\n"


def main() -> int:
    out = ROOT / "web" / "openapi.json"
    text = document()
    if not out.exists() or out.read_text() != text:
        out.write_text(text)
        print(f"{out}: written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
