"""Merged tile statistics under a RAM budget: the rest waits in files, read back on demand.

A tile's accumulators take 76 bytes a pixel (TileAccumulator.BYTES_PER_PIXEL, from the channel
table; more with the outputs a job's `aovs` turns on), so an 8192x8192 job holds 5.1 GB of
them. TileCache keeps the most recently used tiles of every job in RAM up to its budget
(RENDERFARM_TILE_CACHE_MB); when a tile is needed past it, the least recently used ones are
written to their job's file in the scratch directory (DATA_DIR/scratch/JOB.tiles) and their
arrays let go. A merge of an evicted tile reads it back
first (TileCache.use); a checkpoint or an image reads an evicted tile from its file in another
thread (SpillRef) without bringing it back into RAM. The files are scratch: the database stays
the only durable store, so they are removed when the job is forgotten and at start.

Nothing here changes a value: the arrays are written and read back bit for bit, so a spilled
job merges to exactly the image it would have in RAM.

Copy on write, as in RAM: an evicted tile's file slot is never overwritten while a reader holds
it. Every eviction writes to a free slot, and a slot is freed only when neither its tile nor a
reader refers to it (SpillFile.retain/release). All bookkeeping runs on the event loop, except
that readers in other threads read and release their slots (under the file's lock).
"""

from __future__ import annotations

import ctypes
import math
import os
import shutil
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..domain import channels
from ..domain.merge import Snapshot, TileAccumulator


def _shapes(
    width: int, height: int, layout: channels.Layout
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of each array of a width x height tile of a job's layout, in file
    order (the channel table's)."""
    return {a.name: (a.shape(width, height), np.dtype(a.dtype)) for a in layout.stored()}


class SpillFile:
    """One job's evicted tiles: fixed-size slots of one file, reused once nobody reads them."""

    def __init__(self, path: Path, slot_bytes: int):
        self.path = path
        self.slot_bytes = slot_bytes
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
        self._lock = threading.Lock()
        self._owned: set[int] = set()  # slots holding some tile's current arrays
        self._readers: dict[int, int] = {}  # slot -> snapshots not read yet
        self._free: list[int] = []
        self.slots = 0  # slots the file has grown to
        self._removed = False

    def allocate(self) -> int:
        """A free slot, owned by the tile about to be written to it."""
        with self._lock:
            slot = self._free.pop() if self._free else self.slots
            self.slots = max(self.slots, slot + 1)
            self._owned.add(slot)
            return slot

    def disown(self, slot: int) -> None:
        """The tile has moved on: the slot is free once its readers are done."""
        with self._lock:
            self._owned.discard(slot)
            if slot not in self._readers:
                self._free.append(slot)

    def retain(self, slot: int) -> None:
        with self._lock:
            self._readers[slot] = self._readers.get(slot, 0) + 1

    def release(self, slot: int) -> None:
        with self._lock:
            left = self._readers[slot] - 1
            if left:
                self._readers[slot] = left
                return
            del self._readers[slot]
            if slot not in self._owned:
                self._free.append(slot)
            if self._removed and not self._readers:
                self._close()

    def write(self, slot: int, arrays: list[np.ndarray]) -> None:
        buffers = [memoryview(np.ascontiguousarray(a)).cast("B") for a in arrays]
        expected = sum(len(b) for b in buffers)
        offset = slot * self.slot_bytes
        written = os.pwritev(self.fd, buffers, offset)
        if written != expected:  # a short write (disk full): finish it or fail loudly
            data = b"".join(buffers)
            while written < expected:
                n = os.pwrite(self.fd, data[written:], offset + written)
                if n <= 0:
                    raise OSError(f"cannot write {self.path}")
                written += n

    def read(self, slot: int, arrays: list[np.ndarray], offset: int = 0) -> None:
        """Fill `arrays` (C-contiguous, one after the other in the file) from the slot, from
        `offset` bytes into it; the caller holds the slot."""
        buffers = [memoryview(a).cast("B") for a in arrays]
        expected = sum(len(b) for b in buffers)
        got = os.preadv(self.fd, buffers, slot * self.slot_bytes + offset)
        if got != expected:
            raise OSError(f"{self.path}: slot {slot} has {got} of {expected} bytes")

    def remove(self) -> None:
        """Delete the file now; the descriptor closes once the last reader lets go."""
        with self._lock:
            if self._removed:
                return
            self._removed = True
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
            if not self._readers:
                self._close()

    def _close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    @property
    def size_bytes(self) -> int:
        return self.slots * self.slot_bytes


class SpillRef:
    """A snapshot of an evicted tile's statistics or AOVs: its slot, held until read once."""

    __slots__ = ("file", "slot", "names", "width", "height", "layout")

    def __init__(self, file: SpillFile, slot: int, names: tuple, width: int, height: int, layout):
        file.retain(slot)
        self.file, self.slot, self.names = file, slot, names
        self.width, self.height, self.layout = width, height, layout

    def read(self) -> tuple:
        """The arrays, read from the file (in any thread); the slot is released after."""
        if self.slot is None:
            raise RuntimeError("a spilled snapshot is read once")
        shapes = _shapes(self.width, self.height, self.layout)
        arrays = {name: np.empty(*shapes[name]) for name in self.names}
        try:
            # The slot holds the layout's arrays in file order: one read for each run of wanted
            # ones (an image of one layer reads a third of the tile or less).
            offset, run, start = 0, [], 0
            for name in shapes:
                if name in arrays:
                    if not run:
                        start = offset
                    run.append(arrays[name])
                elif run:
                    self.file.read(self.slot, run, start)
                    run = []
                shape, dtype = shapes[name]
                offset += np.dtype(dtype).itemsize * math.prod(shape)
            if run:
                self.file.read(self.slot, run, start)
        finally:
            self._release()
        return tuple(arrays[name] for name in self.names)

    def _release(self) -> None:
        slot, self.slot = self.slot, None
        if slot is not None:
            self.file.release(slot)

    def __del__(self):  # a snapshot dropped unread (a failed checkpoint) frees its slot too
        self._release()


def _trim() -> None:
    """Hand freed heap memory back to the system. The arrays of a tile are below glibc's
    mmap threshold (server.tune_allocator raises it), so a job's worth of them freed stays in
    the heap, counted in the server's RSS, until malloc_trim returns the free pages."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class _Home:
    """Where a cached accumulator belongs: its job, and the file slot holding its arrays."""

    __slots__ = ("job_id", "slot_bytes", "slot", "slot_batches")

    def __init__(self, job_id: str, slot_bytes: int):
        self.job_id = job_id
        self.slot_bytes = slot_bytes
        self.slot: int | None = None
        self.slot_batches = -1  # the accumulator's batch count when the slot was written


class TileCache:
    """The RAM budget of every job's tile accumulators, least recently used first out."""

    def __init__(self, directory: Path, budget_bytes: int):
        self.directory = Path(directory)
        self.budget_bytes = budget_bytes
        self.resident_bytes = 0
        self._lru: OrderedDict[TileAccumulator, None] = OrderedDict()
        self._files: dict[str, SpillFile] = {}
        self.evictions = 0

    def clear_directory(self) -> None:
        """Remove what a previous run left behind (scratch only; the database has it all)."""
        if self.directory.exists():
            shutil.rmtree(self.directory, ignore_errors=True)

    # ------------------------------------------------------------------------ tiles
    def register(self, job_id: str, acc: TileAccumulator, tile_size: int) -> None:
        """Put an accumulator of a job with this tile size under the cache. One that has
        samples counts against the budget at once (and may send others to their files); one
        without keeps no arrays until it is used."""
        if acc.spill is not None:
            return
        slot_bytes = acc.layout.bytes_per_pixel() * tile_size * tile_size
        acc.spill = _Handle(self, acc, _Home(job_id, slot_bytes))
        if acc.batches == 0:
            if acc.resident:
                acc.drop_arrays()
            return
        if acc.resident:
            self._lru[acc] = None
            self.resident_bytes += acc.nbytes
            self._evict_over_budget(keep=acc)

    def use(self, acc: TileAccumulator) -> None:
        """Make the accumulator's arrays resident (read back or zero-filled) and most
        recently used; evict others past the budget."""
        handle = acc.spill
        if handle is None:
            return
        if acc.resident:
            self._lru.move_to_end(acc)
            return
        home = handle.home
        if home.slot is not None and home.slot_batches == acc.batches:
            file = self._files[home.job_id]
            shapes = _shapes(acc.width, acc.height, acc.layout)
            arrays = [np.empty(*shape) for shape in shapes.values()]
            file.read(home.slot, arrays)
            for name, a in zip(shapes, arrays, strict=True):
                setattr(acc, name, a)
        elif acc.batches == 0:
            acc.zero_arrays()
        else:
            raise RuntimeError("an evicted tile has no copy of its merged batches")
        self._lru[acc] = None
        self.resident_bytes += acc.nbytes
        self._evict_over_budget(keep=acc)

    def _evict_over_budget(self, keep: TileAccumulator) -> None:
        while self.resident_bytes > self.budget_bytes and len(self._lru) > 1:
            acc = next(iter(self._lru))
            if acc is keep:
                self._lru.move_to_end(acc)
                continue
            self._evict(acc)

    def _evict(self, acc: TileAccumulator) -> None:
        home = acc.spill.home
        if acc.batches and home.slot_batches != acc.batches:
            file = self._files.get(home.job_id)
            if file is None:
                self.directory.mkdir(parents=True, exist_ok=True)
                file = SpillFile(self.directory / f"{home.job_id}.tiles", home.slot_bytes)
                self._files[home.job_id] = file
            if home.slot is not None:
                file.disown(home.slot)  # free for reuse unless a reader still holds it
            home.slot = file.allocate()
            file.write(home.slot, [getattr(acc, name) for name in acc.arrays])
            home.slot_batches = acc.batches
        del self._lru[acc]
        self.resident_bytes -= acc.nbytes
        acc.drop_arrays()
        self.evictions += 1

    # ------------------------------------------------------------------------- jobs
    def evict_job(self, job_id: str, limit_bytes: int) -> bool:
        """If the job has spilled, send up to limit_bytes of its resident tiles to its file
        (a finished job's RAM goes back at once; its images read the file). True while more
        are left."""
        if job_id not in self._files:
            return False
        resident = [a for a in self._lru if a.spill.home.job_id == job_id]
        freed = 0
        for acc in resident:
            if freed >= limit_bytes:
                return True
            freed += acc.nbytes
            self._evict(acc)
        _trim()
        return False

    def forget_job(self, job_id: str) -> None:
        """Drop the job's tiles from RAM and remove its file."""
        for acc in [a for a in self._lru if a.spill.home.job_id == job_id]:
            del self._lru[acc]
            self.resident_bytes -= acc.nbytes
        file = self._files.pop(job_id, None)
        if file is not None:
            file.remove()
        _trim()

    def close(self) -> None:
        """Remove every file (the server is stopping)."""
        for job_id in list(self._files):
            self.forget_job(job_id)

    @property
    def spill_bytes(self) -> int:
        """Bytes of the files (slots written so far)."""
        return sum(f.size_bytes for f in self._files.values())


class _Handle:
    """acc.spill of a cached accumulator: what its snapshots need while it is evicted."""

    __slots__ = ("cache", "home", "width", "height", "layout")

    def __init__(self, cache: TileCache, acc: TileAccumulator, home: _Home):
        self.cache, self.home = cache, home
        self.width, self.height, self.layout = acc.width, acc.height, acc.layout

    def reference(self, names: tuple) -> SpillRef | Snapshot:
        """A snapshot of the evicted arrays named (TileAccumulator.snapshot on an evicted
        tile)."""
        home = self.home
        if home.slot is None:  # never merged: zeros (read by nobody but images)
            shapes = _shapes(self.width, self.height, self.layout)
            return Snapshot(names, (np.zeros(*shapes[name]) for name in names))
        file = self.cache._files[home.job_id]
        return SpillRef(file, home.slot, names, self.width, self.height, self.layout)
