"""Cryptomatte (#40): ID mattes by glTF node, material and root node, as the Cryptomatte
specification (Psyop, version 1.1.0) defines them, from the channel table's ranked rows.

What the workers send and the server keeps (channels.py, Accumulate.RANKED): per pixel RANKS
(label, count) pairs, uint32: a label is a glTF index plus one (0: an empty slot) and its count
the samples of the pixel whose camera ray's first hit had it. Misses are not counted: the
background is what the counts leave uncovered. Merging adds the counts of equal labels and keeps
the RANKS largest (ties: the smaller label first), so a pixel's pairs are a function of its
batches in order, wherever they were rendered.

What an EXR gets (the specification's "EXR File"): for each type, layers {type}00, {type}01 and
{type}02 whose R and B hold the IDs of ranks 2k and 2k + 1 and G and A their coverage (count /
samples: the share of the pixel's samples, the farm's box pixel filter), and header attributes
cryptomatte/{key}/name, hash (MurmurHash3_32), conversion (uint32_to_float32) and manifest (a
JSON object of name -> 8 hex digits of the ID's float bits). The ID of a name is MurmurHash3_32
(seed 0) of its UTF-8 bytes with the float's exponent clamped to 1..254; the key, the first 7
hex digits of the hash of the type's name, as Blender and the reference implementations do.

Names: CryptoObject by the glTF node's `name`, CryptoMaterial by the material's, CryptoAsset by
the name of the node's root (its ancestor in the scene's `nodes`; itself if it has none). An
unnamed node is `nodes[i]`, an unnamed material `materials[i]`, and primitives without a
material are `default material` (glTF's default). Nodes (or materials) of one name share an ID,
as the specification intends ("where these string values overlap, the IDs will be combined").
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

import mmh3
import numpy as np

from .. import _kernels
from . import channels
from .scenes.glb import parse_json

# Ranks kept per pixel and type: the specification's suggested 6 levels (3 layers), the
# channel table's.
RANKS = channels.CRYPTO_RANKS
LEVELS = RANKS // 2  # layers {type}00 ... {type}02
# The label of a sample that hit a primitive without a material (glTF's default material) in
# the material row: glTF material labels are their index plus one, 0 an empty slot.
DEFAULT_MATERIAL_LABEL = 0xFFFFFFFF
DEFAULT_MATERIAL_NAME = "default material"
TYPES = ("CryptoObject", "CryptoMaterial", "CryptoAsset")


def hash_bits(name: str) -> int:
    """The float bits of a name's ID: MurmurHash3_32 (seed 0) of its UTF-8 bytes, its exponent
    clamped to 1..254 (no zero, denormal, inf or NaN)."""
    h = mmh3.hash(name.encode("utf-8"), 0, signed=False)
    exponent = min(max((h >> 23) & 0xFF, 1), 254)
    return (h & 0x807FFFFF) | (exponent << 23)


def hash_float(name: str) -> float:
    """A name's ID as the float32 a pixel holds."""
    return struct.unpack("<f", struct.pack("<I", hash_bits(name)))[0]


def metadata_key(type_name: str) -> str:
    """The 7 hex digits that key a type's header attributes (cryptomatte/{key}/...)."""
    return f"{mmh3.hash(type_name.encode('utf-8'), 0, signed=False):08x}"[:7]


# ------------------------------------------------------------------------------- the merge
def _combine(labels: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) labels and counts with equal labels of a row added into one slot (0, 0 in the
    others), ranked by count descending then label ascending, empty slots last."""
    order = np.argsort(labels, axis=1, kind="stable")
    labels = np.take_along_axis(labels, order, 1)
    counts = np.take_along_axis(counts, order, 1).astype(np.uint64)
    for k in range(1, labels.shape[1]):  # runs of a label: summed into their last slot
        same = (labels[:, k] == labels[:, k - 1]) & (labels[:, k] != 0)
        counts[:, k] += np.where(same, counts[:, k - 1], 0)
        counts[:, k - 1] = np.where(same, 0, counts[:, k - 1])
        labels[:, k - 1] = np.where(same, 0, labels[:, k - 1])
    return _ranked_order(labels, counts)


def merge_ranked(stored: np.ndarray, batch: np.ndarray) -> np.ndarray:
    """Two sets of ranked pairs (..., 2 RANKS) uint32 merged: counts of equal labels added, the
    RANKS largest kept (the stored array's shape). Each set holds a label at most once. One
    pass in C (_kernels.merge_ranked): under a millisecond for a 64x64 tile."""
    a = np.ascontiguousarray(stored, np.uint32)
    b = np.ascontiguousarray(batch, np.uint32).reshape(a.shape)
    out = np.empty_like(a)
    _kernels.merge_ranked(a, b, out, a.size // (2 * RANKS), RANKS)
    return out


def _ranked_order(labels: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) distinct labels and their counts ranked by count descending, then label
    ascending; empty slots (label 0) last, as (0, 0)."""
    counts = np.where(labels != 0, counts, 0).astype(np.uint64)
    key = ((np.uint64(0xFFFFFFFF) - counts) << np.uint64(32)) | labels.astype(np.uint64)
    key = np.where(labels != 0, key, np.uint64(0xFFFFFFFFFFFFFFFF))
    order = np.argsort(key, axis=1)  # keys are distinct but for empty slots, all (0, 0)
    labels = np.take_along_axis(labels, order, 1)
    counts = np.take_along_axis(counts, order, 1)
    return labels, np.minimum(counts, 0xFFFFFFFF).astype(np.uint32)


def regroup(pairs: np.ndarray, mapping: np.ndarray) -> np.ndarray:
    """Ranked pairs (..., 2 RANKS) with each label replaced by mapping[label] (a coarser label:
    a node's root) and the counts of the labels that became equal added, re-ranked."""
    shape = pairs.shape
    p = np.asarray(pairs, np.uint32).reshape(-1, RANKS, 2)
    labels = np.where(p[..., 0] < len(mapping), mapping[np.minimum(p[..., 0], len(mapping) - 1)],
                      0).astype(np.uint32)  # fmt: skip
    labels, counts = _combine(labels, p[..., 1])
    return np.ascontiguousarray(np.stack([labels, counts], -1).reshape(shape))


# ------------------------------------------------------------------------------- the names
@dataclass(frozen=True)
class Names:
    """A scene's Cryptomatte names by label, for each type: `names[type][label]` ("" for a
    label no name has: 0), and for CryptoAsset the node label -> root node label map."""

    objects: tuple[str, ...]
    materials: dict[int, str]
    roots: np.ndarray  # uint32, indexed by node label: the root node's label

    @classmethod
    def of(cls, document: dict[str, Any]) -> Names:
        nodes = document.get("nodes") or []
        materials = document.get("materials") or []

        def name(items: list, i: int, kind: str) -> str:
            item = items[i] if isinstance(items[i], dict) else {}
            value = item.get("name")
            return value if isinstance(value, str) and value else f"{kind}[{i}]"

        objects = ("",) + tuple(name(nodes, i, "nodes") for i in range(len(nodes)))
        by_label = {i + 1: name(materials, i, "materials") for i in range(len(materials))}
        by_label[DEFAULT_MATERIAL_LABEL] = DEFAULT_MATERIAL_NAME
        parent = {}
        for i, node in enumerate(nodes):
            for child in (node.get("children") or []) if isinstance(node, dict) else []:
                if isinstance(child, int) and 0 <= child < len(nodes):
                    parent.setdefault(child, i)
        roots = np.zeros(len(nodes) + 1, np.uint32)
        for i in range(len(nodes)):
            root, seen = i, {i}
            while root in parent and parent[root] not in seen:  # (a cycle is refused at upload)
                root = parent[root]
                seen.add(root)
            roots[i + 1] = root + 1
        return cls(objects, by_label, roots)

    def label_names(self, type_name: str) -> dict[int, str]:
        """The names of a type's labels (CryptoAsset: by root node label)."""
        if type_name == "CryptoMaterial":
            return self.materials
        objects = {i: n for i, n in enumerate(self.objects) if i}
        if type_name == "CryptoObject":
            return objects
        return {int(r): objects[int(r)] for r in set(self.roots[1:].tolist())}

    def id_table(self, type_name: str) -> dict[int, float]:
        """label -> the float32 ID its name hashes to."""
        return {label: hash_float(n) for label, n in self.label_names(type_name).items()}

    def header(self, type_name: str) -> dict[str, str]:
        """A type's EXR header attributes, with the manifest of every name it may show."""
        key = f"cryptomatte/{metadata_key(type_name)}"
        manifest = {n: f"{hash_bits(n):08x}" for n in sorted(set(self.label_names(type_name)
                                                                   .values()))}  # fmt: skip
        return {
            f"{key}/name": type_name,
            f"{key}/hash": "MurmurHash3_32",
            f"{key}/conversion": "uint32_to_float32",
            f"{key}/manifest": json.dumps(
                manifest, sort_keys=True, separators=(",", ":"), ensure_ascii=False
            ),  # fmt: skip
        }


def names_of_json(raw: bytes) -> Names:
    """Names.of a glTF JSON document's bytes (a SceneError for malformed JSON)."""
    document = parse_json(raw, "scene")
    return Names.of(document if isinstance(document, dict) else {})


def exr_values(pairs: np.ndarray, samples, ids: dict[int, float]) -> np.ndarray:
    """The EXR values of ranked pairs (h, w, 2 RANKS): (h, w, 2 RANKS) float32, per rank the ID
    of its label's name (0 for an empty slot, or a label without a name) and its coverage,
    count / samples (a count, or each pixel's, (h, w), with per-pixel adaptive sampling)."""
    p = np.asarray(pairs, np.uint32)
    labels, counts = p[..., 0::2], p[..., 1::2]
    out = np.zeros(p.shape, np.float32)
    known = np.array(sorted(ids), np.uint32)
    if known.size:
        values = np.array([ids[int(k)] for k in known], np.float32)
        at = np.minimum(np.searchsorted(known, labels), known.size - 1)
        found = (known[at] == labels) & (labels != 0)
        out[..., 0::2] = np.where(found, values[at], np.float32(0))
    else:
        found = np.zeros(labels.shape, bool)
    n = np.maximum(np.asarray(samples, np.float64), 1.0)
    out[..., 1::2] = np.where(found, counts / (n[..., None] if n.ndim else n), 0.0)
    return out
