#!/usr/bin/env python3
"""Write a small still life as glTF 2.0, studio.glb: a potted plant, a gold vase, a tinted glass
ball and a lacquered box on a tiled floor in front of a plaster wall, lit by a soft box and a
spot light.

What it exercises of the renderer (docs/scenes.md): a floor of glazed tiles whose base colour,
normal map and metallic-roughness map (rough, thin grout lines between glossy tiles) are
generated here; a smooth metal (gold) lathed vase; glass with KHR_materials_transmission,
KHR_materials_ior and KHR_materials_volume (a blue-green tint that deepens with the length of
glass a ray crosses); leaves that are alpha-masked cards (alphaMode MASK, a generated RGBA leaf
texture, doubleSided); a box under KHR_materials_clearcoat; one emissive area light
(KHR_materials_emissive_strength), one KHR_lights_punctual spot light and a camera. About 24,000
triangles and four PNG textures (encoded here with zlib, no imaging library).

Usage:
    python make_studio.py                # write studio.glb next to this script
    python make_studio.py -o OUT.glb     # write it elsewhere
    renderfarm render examples/studio.glb -o out/studio.exr --width 512 --height 384 \\
        --noise-threshold 0.1 --max-spp 512

Only the standard library is used, so any Python 3.10+ runs it. The output is a pure function
of this file: two runs write the same bytes.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import zlib
from pathlib import Path

# ---- vector helpers (tuples of floats)


def add(a, b):
    return tuple(x + y for x, y in zip(a, b, strict=True))


def sub(a, b):
    return tuple(x - y for x, y in zip(a, b, strict=True))


def scale(a, s):
    return tuple(x * s for x in a)


def dot(a, b):
    return sum(x * y for x, y in zip(a, b, strict=True))


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def normalize(v):
    n = math.sqrt(dot(v, v))
    return tuple(x / n for x in v)


def quat_axis_angle(axis, angle):
    axis = normalize(axis)
    s = math.sin(angle / 2)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2))


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def look_rotation(eye, target):
    """The rotation that turns a node looking down its -Z (a glTF camera or spot light, +Y up)
    from eye toward target: yaw about +Y, then pitch about the node's +X."""
    d = normalize(sub(target, eye))
    yaw = math.atan2(-d[0], -d[2])
    pitch = math.asin(max(-1.0, min(1.0, d[1])))
    return quat_mul(quat_axis_angle((0, 1, 0), yaw), quat_axis_angle((1, 0, 0), pitch))


def smoothstep(e0, e1, x):
    t = min(1.0, max(0.0, (x - e0) / (e1 - e0)))
    return t * t * (3.0 - 2.0 * t)


# ---- deterministic noise: an integer hash, and periodic value noise built on it


def hash01(*ints: int) -> float:
    """A number in [0, 1) from integers (a 32-bit integer hash; no global random state)."""
    h = 0x811C9DC5
    for i in ints:
        h = ((h ^ (i & 0xFFFFFFFF)) * 0x01000193) & 0xFFFFFFFF
        h ^= h >> 15
        h = (h * 0x2C1B3C6D) & 0xFFFFFFFF
        h ^= h >> 12
        h = (h * 0x297A2D39) & 0xFFFFFFFF
        h ^= h >> 15
    return h / 2**32


class PeriodicNoise:
    """Value noise on a period x period lattice (smooth between lattice points) that wraps, so
    a texture made with it tiles without seams when its size is a multiple of the cell."""

    def __init__(self, period: int, seed: int):
        self.period = period
        self.table = [[hash01(seed, i, j) for i in range(period)] for j in range(period)]

    def __call__(self, x: float, y: float) -> float:
        p = self.period
        ix, iy = math.floor(x), math.floor(y)
        fx, fy = x - ix, y - iy
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
        x0, x1, y0, y1 = ix % p, (ix + 1) % p, iy % p, (iy + 1) % p
        t = self.table
        top = t[y0][x0] + (t[y0][x1] - t[y0][x0]) * fx
        bottom = t[y1][x0] + (t[y1][x1] - t[y1][x0]) * fx
        return top + (bottom - top) * fy


# ---- PNG (8-bit RGB or RGBA, no interlace), as the PNG specification lays it out


def png(width: int, height: int, channels: int, pixels: bytes) -> bytes:
    """pixels: rows top to bottom, `channels` bytes per pixel (3: RGB, 4: RGBA)."""
    assert len(pixels) == width * height * channels
    stride = width * channels
    raw = b"".join(b"\0" + pixels[y * stride : (y + 1) * stride] for y in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    colour_type = {3: 2, 4: 6}[channels]
    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 9))
        + chunk(b"IEND", b"")
    )


def byte(x: float) -> int:
    return max(0, min(255, round(x * 255.0)))


# ---- the tiled floor's three textures

TILE_TEXELS = 512  # the texture's edge
TILES_PER_TEXTURE = 4  # tiles along each edge of the texture
TILE_METRES = 0.2  # so the texture covers 0.8 m of floor and repeats
GROUT_HALF = 2.0  # half the grout line's width, in texels (about 3 mm a side)
BEVEL = 5.0  # the tiles' rounded edge, in texels
GROOVE_DEPTH = 2.0  # how far the grout sits below the tile, in texels


def floor_textures() -> tuple[bytes, bytes, bytes]:
    """Base colour (sRGB), normal map and metallic-roughness map of the tiles, as PNG files.

    Tiles are cream, each a little different, with a mottled glaze; the grout is grey, sunk
    below the tiles (the normal map slopes at the tiles' rounded edges), and rough where the
    glaze is glossy (roughness 0.85 against about 0.2: the metallic-roughness map's thin lines).
    """
    n = TILE_TEXELS
    cell = n // TILES_PER_TEXTURE
    mottle = PeriodicNoise(32, 1)
    fine = PeriodicNoise(128, 2)
    height = [[0.0] * n for _ in range(n)]
    groutness = [[0.0] * n for _ in range(n)]
    for y in range(n):
        dy = (y + 0.5) % cell
        dy = min(dy, cell - dy)
        for x in range(n):
            dx = (x + 0.5) % cell
            d = min(dx, cell - dx, dy)
            g = 1.0 - smoothstep(GROUT_HALF - 0.5, GROUT_HALF + 0.5, d)
            groutness[y][x] = g
            bump = 0.15 * (fine(x / 4.0, y / 4.0) - 0.5)
            height[y][x] = GROOVE_DEPTH * smoothstep(GROUT_HALF, GROUT_HALF + BEVEL, d) + bump

    colour, normal, mr = bytearray(), bytearray(), bytearray()
    tone = [
        [0.9 + 0.2 * hash01(7, i, j) for i in range(TILES_PER_TEXTURE)]
        for j in range(TILES_PER_TEXTURE)
    ]
    for y in range(n):
        for x in range(n):
            g = groutness[y][x]
            m = mottle(x / 16.0, y / 16.0)
            t = tone[y // cell][x // cell] * (0.93 + 0.14 * m)
            tile = (0.86 * t, 0.80 * t, 0.70 * t)  # sRGB, cream
            grout = (0.42, 0.40, 0.37)
            colour += bytes(byte(grout[c] * g + tile[c] * (1.0 - g)) for c in range(3))
            # Tangent space: +X along the texture's +u (right), +Y up the image (towards -v).
            hx = height[y][(x + 1) % n] - height[y][(x - 1) % n]
            hy = height[(y + 1) % n][x] - height[(y - 1) % n][x]
            nx, ny, nz = normalize((-hx / 2.0, hy / 2.0, 1.0))
            normal += bytes((byte(0.5 + 0.5 * nx), byte(0.5 + 0.5 * ny), byte(0.5 + 0.5 * nz)))
            roughness = 0.85 * g + (0.16 + 0.1 * m) * (1.0 - g)
            mr += bytes((255, byte(roughness), 0))  # R unused, G roughness, B metallic
    return png(n, n, 3, bytes(colour)), png(n, n, 3, bytes(normal)), png(n, n, 3, bytes(mr))


# ---- the leaf texture

LEAF_W, LEAF_H = 128, 256
PETIOLE = 0.16  # the stalk's share of the leaf's length
LEAF_GREEN = (0.24, 0.47, 0.16)  # sRGB; also the colour of the cut-away texels


def leaf_half_width(t: float) -> float:
    """Half the leaf's width (in u, 0.5 is the card's edge) at t along it: 0 base, 1 tip."""
    if t < PETIOLE:
        return 0.035
    s = (t - PETIOLE) / (1.0 - PETIOLE)
    return 0.035 + 0.425 * math.sin(math.pi * s**0.7) ** 0.9


def leaf_texture() -> bytes:
    """RGBA: opaque inside the leaf's outline, alpha 0 outside. The card's v runs from the tip
    (v = 0, the image's top row) to the stalk (v = 1). Outside the outline the colour is the
    leaf's green, so that filtering at the edge does not darken it."""
    out = bytearray()
    for y in range(LEAF_H):
        t = 1.0 - (y + 0.5) / LEAF_H
        w = leaf_half_width(t)
        s = max(0.0, (t - PETIOLE) / (1.0 - PETIOLE))
        for x in range(LEAF_W):
            a = abs((x + 0.5) / LEAF_W - 0.5)
            if a >= w:
                out += bytes((*(byte(c) for c in LEAF_GREEN), 0))
                continue
            edge = a / w
            shade = 0.85 + 0.25 * s - 0.2 * edge * edge
            r, g, b = (c * shade for c in LEAF_GREEN)
            midrib = t < PETIOLE or a < 0.012 + 0.01 * (1.0 - s)
            vein = (s - 0.9 * a) * 9.0
            side_vein = abs(vein - round(vein)) < 0.06 and s > 0.05 and edge < 0.9
            if midrib:
                r, g, b = 0.50, 0.66, 0.30
            elif side_vein:
                r, g, b = r * 1.25, g * 1.18, b * 1.1
            out += bytes((byte(r), byte(g), byte(b), 255))
    return png(LEAF_W, LEAF_H, 4, bytes(out))


# ---- meshes: (positions, normals, uvs or None, indices)


def oriented(positions, normals, uvs, triangles):
    """Indices of the triangles, each wound counter-clockwise seen from the side its vertex
    normals point to; triangles of zero area (at a lathe's axis) are dropped."""
    indices = []
    for a, b, c in triangles:
        g = cross(sub(positions[b], positions[a]), sub(positions[c], positions[a]))
        if dot(g, g) < 1e-20:
            continue
        if dot(g, add(add(normals[a], normals[b]), normals[c])) < 0.0:
            b, c = c, b
        indices += [a, b, c]
    return positions, normals, uvs, indices


def quad(corners, uv_of=None):
    """A flat quad (corners counter-clockwise seen from its front)."""
    n = normalize(cross(sub(corners[1], corners[0]), sub(corners[2], corners[0])))
    uvs = [uv_of(p) for p in corners] if uv_of else None
    return oriented(list(corners), [n] * 4, uvs, [(0, 1, 2), (0, 2, 3)])


def box(size, centre, yaw):
    """A cube of edge `size` standing on y = centre[1] - size / 2, turned by yaw about +y."""
    h = size / 2.0
    c, s = math.cos(yaw), math.sin(yaw)

    def place(p):
        x, y, z = p
        return (centre[0] + c * x + s * z, centre[1] + y, centre[2] - s * x + c * z)

    positions, normals, triangles = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = [0.0, 0.0, 0.0]
            n[axis] = sign
            u, v = [(1, 2), (2, 0), (0, 1)][axis]
            base = len(positions)
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = [0.0, 0.0, 0.0]
                p[axis], p[u], p[v] = sign * h, du * h, dv * h
                positions.append(place(tuple(p)))
            normals += [place_dir(tuple(n), c, s)] * 4
            triangles += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return oriented(positions, normals, None, triangles)


def place_dir(n, c, s):
    return (c * n[0] + s * n[2], n[1], -s * n[0] + c * n[2])


def lathe(strips, centre, segments=72):
    """A surface of revolution about the vertical axis through centre. strips: polylines of
    (radius, height) points, each smooth (its own vertex normals; where two strips meet the
    surface has a crease). The profile runs so that the surface's outside is on its right:
    up the outside, down the inside, outwards along a bottom."""
    positions, normals, triangles = [], [], []
    for strip in strips:
        tangents = []
        for i in range(len(strip)):
            a = strip[max(0, i - 1)]
            b = strip[min(len(strip) - 1, i + 1)]
            tangents.append(normalize((b[0] - a[0], b[1] - a[1])))
        first = len(positions)
        for (r, y), (tr, ty) in zip(strip, tangents, strict=True):
            nr, ny = ty, -tr  # the tangent turned clockwise: the outside
            for k in range(segments):
                phi = 2.0 * math.pi * k / segments
                c, s = math.cos(phi), math.sin(phi)
                positions.append((centre[0] + r * c, centre[1] + y, centre[2] - r * s))
                normals.append((nr * c, ny, -nr * s))
        for i in range(len(strip) - 1):
            for k in range(segments):
                a = first + i * segments + k
                b = first + i * segments + (k + 1) % segments
                triangles += [(a, b, b + segments), (a, b + segments, a + segments)]
    return oriented(positions, normals, None, triangles)


def catmull_rom(points, samples_per_span):
    """A smooth curve through the points (uniform Catmull-Rom), the ends included."""
    out = []
    for i in range(len(points) - 1):
        p0 = points[max(0, i - 1)]
        p1, p2 = points[i], points[i + 1]
        p3 = points[min(len(points) - 1, i + 2)]
        for k in range(samples_per_span):
            t = k / samples_per_span
            t2, t3 = t * t, t * t * t
            out.append(
                tuple(
                    0.5
                    * (
                        2 * p1[c]
                        + (-p0[c] + p2[c]) * t
                        + (2 * p0[c] - 5 * p1[c] + 4 * p2[c] - p3[c]) * t2
                        + (-p0[c] + 3 * p1[c] - 3 * p2[c] + p3[c]) * t3
                    )
                    for c in range(2)
                )
            )
    out.append(points[-1])
    return out


VASE_AT = (0.0, 0.0, -0.45)
# (radius, height) of the vase's outside, foot to lip, in metres.
VASE_PROFILE = ((0.055, 0.0), (0.065, 0.015), (0.105, 0.08), (0.125, 0.15), (0.1, 0.235),
                (0.055, 0.31), (0.045, 0.35), (0.055, 0.4), (0.072, 0.43))  # fmt: skip
WALL = 0.006


def vase():
    outside = catmull_rom(VASE_PROFILE, 8)
    lip_r, lip_y = VASE_PROFILE[-1]
    inside = [(r - WALL, y) for r, y in reversed(catmull_rom(VASE_PROFILE[5:], 8))]
    neck_r, neck_y = inside[-1]
    return lathe(
        [
            [(0.0, 0.0), (VASE_PROFILE[0][0], 0.0)],  # the base, outwards
            outside,
            [(lip_r, lip_y), (lip_r - WALL, lip_y)],  # the lip, inwards
            inside,  # down the neck
            [(neck_r, neck_y), (0.0, neck_y)],  # a floor inside the neck
        ],
        VASE_AT,
    )


GLASS_AT = (0.26, 0.11, -0.02)
GLASS_RADIUS = 0.11


def glass_ball():
    rings = 48
    profile = [
        (
            GLASS_RADIUS * math.sin(math.pi * i / rings),
            -GLASS_RADIUS * math.cos(math.pi * i / rings),
        )
        for i in range(rings + 1)
    ]
    return lathe([profile], GLASS_AT, segments=96)


POT_AT = (-0.38, 0.0, -0.28)
SOIL_Y = 0.175
POT_INNER = 0.118


def pot():
    return lathe(
        [
            [(0.0, 0.0), (0.085, 0.0)],
            [(0.085, 0.0), (0.088, 0.004), (0.122, 0.16), (0.123, 0.165)],
            [(0.123, 0.165), (0.136, 0.168), (0.137, 0.2)],  # the rim's band
            [(0.137, 0.2), (0.124, 0.2)],
            [(0.124, 0.2), (POT_INNER, SOIL_Y)],
        ],
        POT_AT,
        segments=64,
    )


def soil():
    return lathe([[(POT_INNER, SOIL_Y), (0.06, SOIL_Y + 0.008), (0.0, SOIL_Y + 0.01)]], POT_AT, 64)


LEAF_LENGTH = 0.34
LEAF_WIDTH = 0.15
LEAVES = 9


def leaves():
    """LEAVES cards rising from the soil in a spiral (golden angle), arching over: each a grid
    4 x 10 quads, folded a little along its midrib. v = 1 at the stalk, 0 at the tip."""
    positions, normals, uvs, triangles = [], [], [], []
    up = (0.0, 1.0, 0.0)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cols, rows = 4, 10
    for k in range(LEAVES):
        phi = 0.4 + k * golden
        along = (math.sin(phi), 0.0, math.cos(phi))
        side = (math.cos(phi), 0.0, -math.sin(phi))
        lift = math.radians(78.0 - 4.0 * k)  # the first leaves upright, the last more open
        droop = math.radians(70.0 + 6.0 * hash01(11, k))  # how much it arches over
        length = LEAF_LENGTH * (0.8 + 0.35 * hash01(12, k))
        root = (
            POT_AT[0] + 0.02 * along[0],
            SOIL_Y + 0.005,
            POT_AT[2] + 0.02 * along[2],
        )
        spine, frames = [root], []
        for i in range(rows + 1):
            theta = lift - droop * (i / rows) ** 1.5
            d = normalize(add(scale(along, math.cos(theta)), scale(up, math.sin(theta))))
            frames.append((d, normalize(cross(d, side))))  # the upper face
            if i < rows:
                spine.append(add(spine[-1], scale(d, length / rows)))
        first = len(positions)
        for i in range(rows + 1):
            d, n = frames[i]
            for j in range(cols + 1):
                u = j / cols
                off = (u - 0.5) * LEAF_WIDTH
                fold = 0.18 * abs(off)  # the halves rise from the midrib
                positions.append(add(add(spine[i], scale(side, off)), scale(n, fold)))
                tilt = 0.0 if j * 2 == cols else math.copysign(0.18, off)
                normals.append(normalize(sub(n, scale(side, tilt))))
                uvs.append((u, 1.0 - i / rows))
        for i in range(rows):
            for j in range(cols):
                a = first + i * (cols + 1) + j
                b, c, dd = a + 1, a + cols + 2, a + cols + 1
                triangles += [(a, b, c), (a, c, dd)]
    return oriented(positions, normals, uvs, triangles)


# ---- the buffer: accessors and images appended one after another


class Buffer:
    def __init__(self):
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, payload: bytes, target=None) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        v = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(payload)}
        if target is not None:
            v["target"] = target
        self.data += payload
        self.views.append(v)
        return len(self.views) - 1

    def add(self, rows, gltf_type, component=5126, target=34962):
        fmt = {5126: "f", 5123: "H", 5125: "I"}[component]
        flat = [x for r in rows for x in (r if isinstance(r, tuple | list) else (r,))]
        payload = struct.pack(f"<{len(flat)}{fmt}", *flat)
        accessor = {
            "bufferView": self.view(payload, target),
            "componentType": component,
            "count": len(rows),
            "type": gltf_type,
        }
        if gltf_type == "VEC3":  # POSITION needs its bounds; stored as float32 reads them
            stored = struct.unpack(f"<{len(flat)}f", payload)
            accessor["min"] = [min(stored[i::3]) for i in range(3)]
            accessor["max"] = [max(stored[i::3]) for i in range(3)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


# ---- the scene

CAMERA_EYE = (0.0, 0.6, 1.6)
CAMERA_TARGET = (0.02, 0.2, -0.3)
CAMERA_YFOV = math.radians(30.0)
WALL_Z = -1.1
SOFTBOX_CENTRE = (-1.1, 1.9, 1.2)
SOFTBOX_SIZE = (2.0, 1.4)
SOFTBOX_STRENGTH = 4.0
# The spot throws a pool of warm light on the wall above the still life, and only there: its
# cone misses the glossy things (a delta light seen through a glossy reflection from a diffuse
# surface is a caustic a path tracer finds only by chance: fireflies).
SPOT_AT = (0.2, 2.4, 1.0)
SPOT_TARGET = (0.05, 0.85, WALL_Z)
SPOT_INTENSITY = 12.0  # W/sr along the axis (the renderer's irradiance is I / d^2)
SPOT_CONE = (math.radians(5.0), math.radians(10.0))


def build() -> tuple[dict, bytes]:
    buf = Buffer()
    images, textures, materials, meshes, nodes = [], [], [], [], []

    def texture(name, data):
        images.append({"name": name, "mimeType": "image/png", "bufferView": buf.view(data)})
        textures.append({"name": name, "sampler": 0, "source": len(images) - 1})
        return len(textures) - 1

    def material(name, **fields):
        materials.append({"name": name, **fields})
        return len(materials) - 1

    def pbr(color, roughness, metallic=0.0, alpha=1.0):
        return {
            "baseColorFactor": [*color, alpha],
            "metallicFactor": metallic,
            "roughnessFactor": roughness,
        }

    def mesh(name, geometry, mat):
        positions, normals, uvs, indices = geometry
        attributes = {"POSITION": buf.add(positions, "VEC3"), "NORMAL": buf.add(normals, "VEC3")}
        if uvs is not None:
            attributes["TEXCOORD_0"] = buf.add(uvs, "VEC2")
        big = len(positions) > 0xFFFF
        primitive = {
            "attributes": attributes,
            "indices": buf.add(indices, "SCALAR", 5125 if big else 5123, target=34963),
            "material": mat,
        }
        meshes.append({"name": name, "primitives": [primitive]})
        nodes.append({"name": name, "mesh": len(meshes) - 1})
        return len(meshes) - 1

    tile_colour, tile_normal, tile_mr = floor_textures()
    tiles = material(
        "glazed tiles",
        pbrMetallicRoughness={
            **pbr((1.0, 1.0, 1.0), 1.0, 1.0),
            "baseColorTexture": {"index": texture("tiles colour", tile_colour)},
            "metallicRoughnessTexture": {"index": texture("tiles metallic-roughness", tile_mr)},
        },
        normalTexture={"index": texture("tiles normal", tile_normal), "scale": 1.0},
    )
    plaster = material("plaster", pbrMetallicRoughness=pbr((0.62, 0.6, 0.57), 0.9))
    gold = material("gold", pbrMetallicRoughness=pbr((1.0, 0.766, 0.336), 0.18, 1.0))
    glass = material(
        "tinted glass",
        pbrMetallicRoughness=pbr((1.0, 1.0, 1.0), 0.0),
        extensions={
            "KHR_materials_transmission": {"transmissionFactor": 1.0},
            "KHR_materials_ior": {"ior": 1.5},
            "KHR_materials_volume": {
                "thicknessFactor": 2 * GLASS_RADIUS,
                "attenuationDistance": 0.12,
                "attenuationColor": [0.45, 0.78, 0.92],
            },
        },
    )
    lacquer = material(
        "red lacquer",
        pbrMetallicRoughness=pbr((0.45, 0.035, 0.03), 0.55),
        extensions={
            "KHR_materials_clearcoat": {"clearcoatFactor": 1.0, "clearcoatRoughnessFactor": 0.03}
        },
    )
    clay = material("terracotta", pbrMetallicRoughness=pbr((0.5, 0.2, 0.1), 0.85))
    earth = material("soil", pbrMetallicRoughness=pbr((0.06, 0.04, 0.03), 1.0))
    leaf = material(
        "leaf",
        pbrMetallicRoughness={
            **pbr((1.0, 1.0, 1.0), 0.5),
            "baseColorTexture": {"index": texture("leaf", leaf_texture())},
        },
        alphaMode="MASK",
        alphaCutoff=0.5,
        doubleSided=True,
    )
    softbox = material(
        "soft box",
        pbrMetallicRoughness=pbr((0.0, 0.0, 0.0), 1.0),
        emissiveFactor=[1.0, 0.95, 0.88],
        extensions={"KHR_materials_emissive_strength": {"emissiveStrength": SOFTBOX_STRENGTH}},
    )

    # The floor, 0.8 m of texture per repeat; the wall behind, facing the camera.
    x0, x1, z1 = -2.5, 2.5, 2.6
    floor = quad(((x0, 0.0, z1), (x1, 0.0, z1), (x1, 0.0, WALL_Z), (x0, 0.0, WALL_Z)),
                 lambda p: (p[0] / (TILES_PER_TEXTURE * TILE_METRES),
                            p[2] / (TILES_PER_TEXTURE * TILE_METRES)))  # fmt: skip
    mesh("floor", floor, tiles)
    mesh("wall", quad(((x0, 0.0, WALL_Z), (x1, 0.0, WALL_Z), (x1, 2.5, WALL_Z),
                       (x0, 2.5, WALL_Z))), plaster)  # fmt: skip
    mesh("vase", vase(), gold)
    mesh("glass ball", glass_ball(), glass)
    mesh("box", box(0.17, (0.5, 0.085, -0.58), math.radians(32.0)), lacquer)
    mesh("pot", pot(), clay)
    mesh("soil", soil(), earth)
    mesh("leaves", leaves(), leaf)

    # The soft box: a rectangle above and to the front left, facing the still life.
    facing = normalize(sub(CAMERA_TARGET, SOFTBOX_CENTRE))
    right = normalize(cross(facing, (0.0, 1.0, 0.0)))
    top = cross(right, facing)
    hw, hh = SOFTBOX_SIZE[0] / 2, SOFTBOX_SIZE[1] / 2
    corners = [add(add(SOFTBOX_CENTRE, scale(right, sx * hw)), scale(top, sy * hh))
               for sx, sy in ((-1, -1), (-1, 1), (1, 1), (1, -1))]  # fmt: skip
    if dot(cross(sub(corners[1], corners[0]), sub(corners[2], corners[0])), facing) < 0:
        corners.reverse()
    mesh("soft box", quad(corners), softbox)

    nodes.append({"name": "spot", "translation": list(SPOT_AT),
                  "rotation": list(look_rotation(SPOT_AT, SPOT_TARGET)),
                  "extensions": {"KHR_lights_punctual": {"light": 0}}})  # fmt: skip
    nodes.append({"name": "camera", "camera": 0, "translation": list(CAMERA_EYE),
                  "rotation": list(look_rotation(CAMERA_EYE, CAMERA_TARGET))})  # fmt: skip

    used = sorted({e for m in materials for e in m.get("extensions", {})} | {"KHR_lights_punctual"})
    doc = {
        "asset": {"version": "2.0", "generator": "renderfarm examples/make_studio.py"},
        "extensionsUsed": used,
        "extensions": {"KHR_lights_punctual": {"lights": [{
            "name": "spot", "type": "spot", "color": [1.0, 0.86, 0.7],
            "intensity": SPOT_INTENSITY,
            "spot": {"innerConeAngle": SPOT_CONE[0], "outerConeAngle": SPOT_CONE[1]},
        }]}},
        "scene": 0,
        "scenes": [{"name": "studio", "nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "cameras": [{"name": "camera", "type": "perspective", "perspective": {
            "yfov": CAMERA_YFOV, "aspectRatio": 4 / 3, "znear": 0.05, "zfar": 20.0}}],
        "meshes": meshes,
        "materials": materials,
        "textures": textures,
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "images": images,
        "bufferViews": buf.views,
        "accessors": buf.accessors,
        "buffers": [{"byteLength": len(buf.data)}],
    }  # fmt: skip
    return doc, bytes(buf.data)


def glb(doc: dict, binary: bytes) -> bytes:
    """The GLB container (glTF 2.0, 4.4): header, JSON chunk, BIN chunk, each 4-byte aligned."""
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    out = struct.pack("<4sII", b"glTF", 2, total)
    out += struct.pack("<I4s", len(text), b"JSON") + text
    out += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    default = Path(__file__).resolve().with_name("studio.glb")
    parser.add_argument("-o", "--output", type=Path, default=default, help="the .glb to write")
    args = parser.parse_args()
    doc, binary = build()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(glb(doc, binary))
    print(args.output)


if __name__ == "__main__":
    main()
