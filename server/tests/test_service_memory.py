"""The job service over MemoryStore: submission, reading, listing, ownership, cancelling and
deleting, with no database (the store contract, test_store_contract.py, makes what holds here
hold on PostgreSQL too)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from renderfarm.app.auth import Caller
from renderfarm.app.composition import build_farm_service
from renderfarm.domain.jobspec import SettingsError
from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.domain.states import JobState
from renderfarm.errors import Forbidden, NotFound
from renderfarm.infra.config import Settings
from renderfarm.infra.memory_store import MemoryStore

CORNELL = Path(__file__).resolve().parents[2] / "examples" / "cornell-box.gltf"
ANN, BOB, ADMIN = Caller("ann", False), Caller("bob", False), Caller("", True)


def test_jobs_through_the_service_on_memory(tmp_path):
    async def main():
        store = MemoryStore()
        service = build_farm_service(Settings(data_dir=tmp_path), store)
        await service.start()
        try:
            settings = {"width": 32, "height": 16, "tile_size": 16, "max_spp": 2}
            view = await service.submit(
                caller=ANN, scene_data=pack_gltf(CORNELL), scene_sha256="",
                filename="cornell-box.glb", name="first", raw_settings=settings,
            )  # fmt: skip
            with pytest.raises(SettingsError) as bad:
                await service.submit(
                    caller=ANN, scene_data=None, scene_sha256=view.scene_sha256, filename="",
                    name="bad", raw_settings={"sampler": "magic"},
                )  # fmt: skip
            again = await service.get(view.id, ANN)
            row = await store.get_job(view.id)
            with pytest.raises(Forbidden):
                await service.get(view.id, BOB)  # another owner's job
            mine = await service.list(None, 10, "", caller=ANN)
            theirs = await service.list(None, 10, "", caller=BOB)
            cancelled = await service.cancel(view.id, ANN)
            await service.delete(view.id, ADMIN)
            with pytest.raises(NotFound):
                await service.get(view.id, ADMIN)
            return view, bad.value, again, row, mine, theirs, cancelled, store
        finally:
            await service.stop(timeout_s=5)

    view, bad, again, row, mine, theirs, cancelled, store = asyncio.run(main())
    assert view.state in (JobState.QUEUED, JobState.RUNNING) and view.name == "first"
    assert view.settings.width == 32 and view.progress.tiles_total == 2  # 32x16 in 16-px tiles
    assert bad.field == "settings.sampler"
    assert again.id == view.id and row.owner == "ann" and row.settings["max_spp"] == 2
    assert [j.id for j in mine[0]] == [view.id] and theirs[0] == []
    assert cancelled.state == JobState.CANCELLED
    assert asyncio.run(store.get_scene_info(view.scene_sha256)) is None  # deleted with its job
