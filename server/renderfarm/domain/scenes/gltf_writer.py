"""A glTF 2.0 document under construction: typed arrays become accessors over one BIN chunk,
images become buffer views, and the result is a GLB (glb.build_glb). Used by converters that
make glTF from another format (usd_convert.py); nothing here reads or writes files.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .glb import build_glb

ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963

_COMPONENT = {np.dtype(np.float32): 5126, np.dtype(np.uint32): 5125, np.dtype(np.uint16): 5123}
_TYPE = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


class GltfWriter:
    """Collects the parts of one glTF document; `glb()` assembles them."""

    def __init__(self, generator: str):
        self.doc: dict[str, Any] = {"asset": {"version": "2.0", "generator": generator}}
        self.blob = bytearray()
        self.used: set[str] = set()

    def _list(self, key: str) -> list[Any]:
        return self.doc.setdefault(key, [])

    def add(self, key: str, item: dict[str, Any]) -> int:
        """Append `item` to the top-level array `key` and return its index."""
        items = self._list(key)
        items.append(item)
        return len(items) - 1

    def use_extension(self, name: str) -> None:
        self.used.add(name)

    def _view(self, data: bytes, target: int | None = None, stride: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        if stride is not None:
            view["byteStride"] = stride
        self.blob.extend(data)
        return self.add("bufferViews", view)

    def accessor(
        self,
        values: np.ndarray,
        *,
        indices: bool = False,
        bounds: bool = False,
        joints: bool = False,
    ) -> int:
        """An accessor of a (count, n) float32 array (n = 1, 2, 3, 4 or 16), of a flat array
        of triangle indices (uint32, or uint16 when small), or of joint indices (`joints`:
        (count, 4) as uint16, as glTF's JOINTS_n)."""
        if joints:
            array = np.ascontiguousarray(np.rint(values), dtype=np.uint16)
            view = self._view(array.tobytes(), ARRAY_BUFFER)
            return self.add(
                "accessors",
                {"bufferView": view, "componentType": 5123, "count": len(array), "type": "VEC4"},
            )
        if indices:
            flat = np.ascontiguousarray(values, dtype=np.uint32).reshape(-1)
            if flat.size and int(flat.max()) < 65535:
                flat = flat.astype(np.uint16)
            view = self._view(flat.tobytes(), ELEMENT_ARRAY_BUFFER)
            return self.add(
                "accessors",
                {
                    "bufferView": view,
                    "componentType": _COMPONENT[flat.dtype],
                    "count": int(flat.size),
                    "type": "SCALAR",
                },
            )
        array = np.ascontiguousarray(values, dtype=np.float32)
        if array.ndim == 1:
            array = array.reshape(-1, 1)
        width = array.shape[1]
        view = self._view(array.tobytes(), ARRAY_BUFFER if width != 16 else None)
        accessor: dict[str, Any] = {
            "bufferView": view,
            "componentType": 5126,
            "count": int(array.shape[0]),
            "type": _TYPE[width],
        }
        if bounds and array.shape[0]:
            accessor["min"] = [float(v) for v in array.min(axis=0)]
            accessor["max"] = [float(v) for v in array.max(axis=0)]
        return self.add("accessors", accessor)

    def bool_accessor(self, values) -> int:
        """A SCALAR unsigned-byte accessor of booleans (0 false, 1 true): the output of a
        KHR_animation_pointer sampler of a bool property, such as KHR_node_visibility's."""
        array = np.ascontiguousarray(np.asarray(values, dtype=bool), dtype=np.uint8)
        view = self._view(array.tobytes())
        return self.add(
            "accessors",
            {"bufferView": view, "componentType": 5121, "count": int(array.size), "type": "SCALAR"},
        )

    def image(self, data: bytes, mime: str, name: str = "") -> int:
        view = self._view(data)
        image: dict[str, Any] = {"bufferView": view, "mimeType": mime}
        if name:
            image["name"] = name
        return self.add("images", image)

    def glb(self) -> bytes:
        doc = dict(self.doc)
        if self.blob:
            while len(self.blob) % 4:
                self.blob.append(0)
            doc["buffers"] = [{"byteLength": len(self.blob)}]
        if self.used:
            doc["extensionsUsed"] = sorted(self.used)
        return build_glb(doc, bytes(self.blob))


__all__ = ["GltfWriter"]
