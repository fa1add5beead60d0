"""Reading Cryptomatte from an EXR by hand (numpy), for the tests that check the farm's against
the specification and against Blender: a name's ID written out from the specification's sample
code, and a name's coverage summed over the ranks that hold its ID."""

from __future__ import annotations

import struct

import numpy as np

LEVELS = 3  # layers {type}00 .. {type}02: 6 ranks


def murmur_id(name: str) -> float:
    """The Cryptomatte specification's ID of a name: MurmurHash3_32 (mmh3, seed 0) as float32
    bits, the exponent clamped to 1..254."""
    import mmh3

    h = mmh3.hash(name, 0, signed=False)
    exponent = min(max((h >> 23) & 255, 1), 254)
    bits = (h & 0x80000000) | (exponent << 23) | (h & 0x7FFFFF)
    return struct.unpack("<f", struct.pack("<I", bits))[0]


def id_hex(name: str) -> str:
    """The ID's 8 hex digits, as a manifest has them."""
    return f"{struct.unpack('<I', struct.pack('<f', murmur_id(name)))[0]:08x}"


def matte(exr: dict[str, np.ndarray], type_name: str, name: str) -> np.ndarray:
    """A name's coverage per pixel: the coverage of every rank whose ID is the name's."""
    want = np.float32(murmur_id(name))
    out = np.zeros(exr[f"{type_name}00.R"].shape)
    for level in range(LEVELS):
        for id_channel, coverage_channel in (("R", "G"), ("B", "A")):
            ids = exr[f"{type_name}{level:02d}.{id_channel}"]
            out += np.where(ids == want, exr[f"{type_name}{level:02d}.{coverage_channel}"], 0)
    return out
