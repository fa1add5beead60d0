"""What FarmService depends on besides its settings, store and scheduler, as interfaces it is
given (docs/architecture.md, "Composition"): app/composition.py builds the implementations a
server runs with; tests give fakes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from ..infra.usd_import import UsdImport

Clock = Callable[[], float]
"""Unix time in seconds (time.time). FarmService reads it for checkpoint intervals, the
database's retry backoff and workers' connect and heartbeat times; the scheduler it is given
should read the same clock (lease deadlines, time limits, elapsed times)."""


class SceneInspector(Protocol):
    """The judge of uploaded scenes: the workers' own loader (infra/scene_check.SceneChecker)."""

    async def check(self, data: bytes, filename: str, sha256: str) -> dict[str, Any]:
        """The loader's description of the scene, or SceneError naming the fault."""
        ...


class UsdConverter(Protocol):
    """USD uploads to glTF before they are inspected (infra/usd_import.UsdImporter)."""

    def is_usd(self, data: bytes | None, filename: str = "") -> bool: ...

    async def convert(self, data: bytes, filename: str) -> UsdImport: ...
