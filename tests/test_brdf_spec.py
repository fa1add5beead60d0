"""The worker's metallic-roughness BRDF against the glTF 2.0 specification's closed form
(Appendix B, "BRDF Implementation"), evaluated here in numpy and nowhere else.

Each render is a flat, untextured ground (normal +Y) of the dielectric materials of MATERIALS
side by side (two with KHR_materials_specular's weight and colour, two
KHR_materials_pbrSpecularGlossiness, two KHR_materials_anisotropy, two
KHR_materials_iridescence, two KHR_materials_diffuse_transmission), seen by an orthographic
camera from direction V and lit by one directional light (KHR_lights_punctual, intensity I)
from direction L (above the ground, or below it for the diffuse BTDF) over a black world.
Every sample of a
pixel then sees the same point of the same BRDF with the same V and L, and the path tracer's
estimate is exact: the pixel is I x f(V, L) x N.L, with f the spec's

    f = fresnel_mix(ior, diffuse_brdf(baseColor), specular_brdf(roughness^2))
    fresnel_mix: mix(base, layer, F0 + (1 - F0) (1 - |V.H|)^5), F0 = ((ior - 1) / (ior + 1))^2
    specular_brdf = Vis D,  D = a^2 X(N.H) / (pi ((N.H)^2 (a^2 - 1) + 1)^2),
    Vis = X(H.L) X(H.V) / (2 (|N.V| sqrt(a^2 + (1 - a^2)(N.L)^2)
                              + |N.L| sqrt(a^2 + (1 - a^2)(N.V)^2)))

(the height-correlated Smith masking-shadowing function of the spec's "Specular BRDF")
over a grid of view and light elevations and azimuths. This is the dielectric that Blender's
Principled BSDF differs from (docs/parity.md, "Differences to expect"): its diffuse is weighted by
the specular layer's directional albedo instead of 1 - F(V.H), and its GGX by default puts
back the energy lost between microfacets. The spec's discussion of its sample
implementation names both (the "Coupling Diffuse and Specular Reflection" and "Masking-Shadowing
Term and Multiple Scattering" sections). Metals are left out here: the farm adds Kulla and
Conty's multiple-scattering term to the metal lobe, as the spec's "Microfacet Surfaces" note
suggests, which its single-scattering sample formula does not have.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from renderfarm.domain.scenes.glb import build_glb
from renderfarm.infra.images import read_exr

INTENSITY = 2.0
# (baseColor, roughness, ior, specularFactor, specularColorFactor): rough and glossy
# dielectrics, one with KHR_materials_ior, two with KHR_materials_specular (a weight and a
# colour, one of whose channels F0 clamps to 1: 0.04 x 30). SPEC_GLOSS ones are
# KHR_materials_pbrSpecularGlossiness materials written as (diffuseFactor, 1 - glossinessFactor,
# -, -, specularFactor): a grey specular on a coloured diffuse, and the extension's own gold.
SPEC_GLOSS = "specular-glossiness"
MATERIALS = [
    ((0.5, 0.5, 0.5), 0.8, 1.5, 1.0, (1.0, 1.0, 1.0)),  # the parity scenes' floor
    ((0.9, 0.3, 0.1), 0.3, 1.5, 1.0, (1.0, 1.0, 1.0)),
    ((0.2, 0.6, 0.9), 1.0, 1.5, 1.0, (1.0, 1.0, 1.0)),
    ((0.7, 0.7, 0.2), 0.5, 1.8, 1.0, (1.0, 1.0, 1.0)),
    ((0.6, 0.4, 0.3), 0.35, 1.5, 0.7, (0.2, 2.5, 30.0)),
    ((0.1, 0.8, 0.3), 0.6, 1.6, 0.4, (1.0, 0.5, 0.0)),
    ((0.8, 0.2, 0.1), 0.4, SPEC_GLOSS, None, (0.25, 0.25, 0.25)),
    ((0.0, 0.0, 0.0), 0.1, SPEC_GLOSS, None, (1.0, 0.766, 0.336)),
    # KHR_materials_anisotropy (strength, rotation in radians): the ground's TANGENT is +X.
    ((0.5, 0.5, 0.5), 0.3, 1.5, 1.0, (1.0, 1.0, 1.0), {"anisotropy": (0.8, 0.0)}),
    ((0.2, 0.4, 0.9), 0.5, 1.5, 1.0, (1.0, 1.0, 1.0), {"anisotropy": (0.6, 1.0)}),
    # KHR_materials_iridescence (factor, film ior, thickness in nm).
    ((0.3, 0.3, 0.3), 0.3, 1.5, 1.0, (1.0, 1.0, 1.0), {"iridescence": (1.0, 1.3, 400.0)}),
    ((0.1, 0.2, 0.6), 0.45, 1.5, 1.0, (1.0, 1.0, 1.0), {"iridescence": (0.5, 1.8, 250.0)}),
    # KHR_materials_diffuse_transmission (factor, colour): a leaf and a lamp shade.
    (
        (0.2, 0.5, 0.1),
        0.5,
        1.5,
        1.0,
        (1.0, 1.0, 1.0),
        {"diffuse_transmission": (0.6, (0.4, 0.9, 0.2))},
    ),
    (
        (0.9, 0.85, 0.7),
        0.25,
        1.4,
        0.8,
        (1.0, 1.0, 1.0),
        {"diffuse_transmission": (1.0, (1.0, 0.8, 0.6))},
    ),
]
# Every strip's TANGENT (xyz, handedness): bitangent = cross(normal +Y, +X) = -Z.
TANGENT = (1.0, 0.0, 0.0, 1.0)
WIDTH, HEIGHT = 16 * len(MATERIALS), 16
# The ground's strips: material k covers z in [2k - n + 0.2, 2k - n + 1.8], side by side along
# the image's width (x in [-XMAG, XMAG]).
STRIP_CENTRES = [2.0 * k - len(MATERIALS) + 1.0 for k in range(len(MATERIALS))]
XMAG = float(len(MATERIALS))


def direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector at an elevation from the normal (+Y), azimuth from +X towards +Z."""
    t, p = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)])


def frame_matrix(z_axis: np.ndarray, x_hint: np.ndarray, position: np.ndarray) -> list[float]:
    """A glTF node matrix (column-major) whose local +Z is z_axis."""
    z = z_axis / np.linalg.norm(z_axis)
    x = x_hint - z * np.dot(x_hint, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.identity(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, position
    return [float(v) for v in m.T.ravel()]


def ground_scene(path: Path, view: np.ndarray, light: np.ndarray) -> None:
    """The four strips, the camera looking along -view and the light shining along -light."""
    positions, normals, indices = [], [], []
    for k, centre in enumerate(STRIP_CENTRES):
        z0, z1 = centre - 0.8, centre + 0.8
        positions += [[-60, 0, z0], [-60, 0, z1], [60, 0, z1], [60, 0, z0]]
        normals += [[0, 1, 0]] * 4
        b = 4 * k
        indices += [b, b + 1, b + 2, b, b + 2, b + 3]  # counter-clockwise seen from +Y
    pos = np.asarray(positions, np.float32)
    n = len(positions)
    blob = pos.tobytes() + np.asarray(normals, np.float32).tobytes()
    blob += np.asarray([TANGENT] * n, np.float32).tobytes()
    index_offset = len(blob)
    blob += np.asarray(indices, np.uint16).tobytes()
    views = [
        {"buffer": 0, "byteOffset": 0, "byteLength": 12 * n},
        {"buffer": 0, "byteOffset": 12 * n, "byteLength": 12 * n},
        {"buffer": 0, "byteOffset": 24 * n, "byteLength": 16 * n},
    ]
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
         "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
        {"bufferView": 1, "componentType": 5126, "count": n, "type": "VEC3"},
        {"bufferView": 2, "componentType": 5126, "count": n, "type": "VEC4"},
    ]  # fmt: skip
    primitives, materials = [], []
    for k, entry in enumerate(MATERIALS):
        colour, roughness, ior, specular, specular_colour = entry[:5]
        views.append({"buffer": 0, "byteOffset": index_offset + 12 * k, "byteLength": 12})
        accessors.append({"bufferView": 3 + k, "componentType": 5123, "count": 6,
                          "type": "SCALAR"})  # fmt: skip
        primitives.append({"attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2},
                           "indices": 3 + k, "material": k})  # fmt: skip
        material = {"pbrMetallicRoughness": {"baseColorFactor": [*colour, 1.0],
                                             "metallicFactor": 0.0,
                                             "roughnessFactor": roughness}}  # fmt: skip
        extensions = {}
        if ior == SPEC_GLOSS:
            # The metallic-roughness fallback above must not be what renders.
            extensions["KHR_materials_pbrSpecularGlossiness"] = {
                "diffuseFactor": [*colour, 1.0],
                "specularFactor": list(specular_colour),
                "glossinessFactor": 1.0 - roughness,
            }
            material["pbrMetallicRoughness"]["baseColorFactor"] = [1.0, 0.0, 1.0, 1.0]
        elif ior != 1.5:
            extensions["KHR_materials_ior"] = {"ior": ior}
        if ior != SPEC_GLOSS and (specular != 1.0 or specular_colour != (1.0, 1.0, 1.0)):
            extensions["KHR_materials_specular"] = {
                "specularFactor": specular,
                "specularColorFactor": list(specular_colour),
            }
        extras = entry[5] if len(entry) > 5 else {}
        if "anisotropy" in extras:
            strength, rotation = extras["anisotropy"]
            extensions["KHR_materials_anisotropy"] = {
                "anisotropyStrength": strength,
                "anisotropyRotation": rotation,
            }
        if "iridescence" in extras:
            factor, film_ior, thickness = extras["iridescence"]
            extensions["KHR_materials_iridescence"] = {
                "iridescenceFactor": factor,
                "iridescenceIor": film_ior,
                "iridescenceThicknessMaximum": thickness,
            }
        if "diffuse_transmission" in extras:
            factor, dt_colour = extras["diffuse_transmission"]
            extensions["KHR_materials_diffuse_transmission"] = {
                "diffuseTransmissionFactor": factor,
                "diffuseTransmissionColorFactor": list(dt_colour),
            }
        if extensions:
            material["extensions"] = extensions
        materials.append(material)
    # Image right is world +Z (the strips side by side); the camera 30 units out along view.
    camera_matrix = frame_matrix(view, np.array([0.0, 0.0, 1.0]), 30.0 * view)
    light_matrix = frame_matrix(light, np.array([0.3, 0.1, 0.9]), 10.0 * light)
    gltf = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_ior", "KHR_materials_specular",
                           "KHR_materials_pbrSpecularGlossiness", "KHR_materials_anisotropy",
                           "KHR_materials_iridescence", "KHR_materials_diffuse_transmission"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "directional", "color": [1, 1, 1], "intensity": INTENSITY}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"mesh": 0},
            {"camera": 0, "matrix": camera_matrix},
            {"matrix": light_matrix, "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [{"type": "orthographic", "orthographic": {
            "xmag": XMAG, "ymag": XMAG * HEIGHT / WIDTH, "znear": 0.1, "zfar": 100.0}}],
        "meshes": [{"primitives": primitives}],
        "materials": materials,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }  # fmt: skip
    path.write_bytes(build_glb(gltf, blob))


def spec_brdf(
    colour,
    roughness,
    ior,
    specular,
    specular_colour,
    *rest,
    v: np.ndarray,
    light: np.ndarray,
) -> np.ndarray:
    """glTF 2.0 Appendix B, the dielectric (metallic 0), with KHR_materials_specular's
    fresnel_mix (its "Implementation" section):

        f0 = min(((ior - 1) / (ior + 1))^2 specularColor, 1),  Fr = f0 + (1 - f0)(1 - |V.H|)^5,
        f = (1 - specular max(Fr)) diffuse + specular Fr specular_brdf,

    f(V, L) for normal +Y, RGB; specular 1 and a white colour give Appendix B's mix. For
    KHR_materials_pbrSpecularGlossiness (ior == SPEC_GLOSS) its BRDF inputs in Appendix B's
    form: c_diff = diffuse (1 - max(specular)), F0 = specular, alpha = (1 - glossiness)^2, and
    f = (1 - F) c_diff / pi + F specular_brdf per channel. With KHR_materials_anisotropy
    (rest = ((strength, rotation),)) specular_brdf is the extension's
    BRDF_specularAnisotropicGGX: at = mix(alpha, 1, strength^2) along the tangent rotated by
    rotation counter-clockwise towards the bitangent, ab = alpha across it,
    D = a2 w2^2 / pi with a2 = at ab, w2 = a2 / |(ab T.H, at B.H, a2 N.H)|^2, and
    V = 0.5 / (N.L |(at T.V, ab B.V, N.V)| + N.V |(at T.L, ab B.L, N.L)|).

    With KHR_materials_diffuse_transmission (rest = ({"diffuse_transmission": (d, C)},)) the
    diffuse term is the extension's mix(diffuse_brdf(baseColor), diffuse_btdf(C), d): the BRDF
    above weighted by 1 - d, and for L below the surface the BTDF
    (1 - specular max(Fr)) d C / pi, Fr at the half vector of V and L mirrored above the
    surface (the farm's choice of the angle, which the extension leaves open; docs/scenes.md).
    Below the surface every other material reflects nothing."""
    n = np.array([0.0, 1.0, 0.0])
    extras = rest[0] if rest else {}
    dt, dt_colour = extras.get("diffuse_transmission", (0.0, (1.0, 1.0, 1.0)))
    if light[1] < 0.0:
        if not dt:
            return np.zeros(3)
        mirrored = light * np.array([1.0, -1.0, 1.0])
        hm = (v + mirrored) / np.linalg.norm(v + mirrored)
        f0 = np.minimum(((1.0 - ior) / (1.0 + ior)) ** 2 * np.asarray(specular_colour), 1.0)
        fr = f0 + (1.0 - f0) * (1.0 - abs(np.dot(v, hm))) ** 5
        return (1.0 - specular * np.max(fr)) * dt * np.asarray(dt_colour) / np.pi
    h = (v + light) / np.linalg.norm(v + light)
    nl, nv, nh = np.dot(n, light), np.dot(n, v), np.dot(n, h)
    vh, hl = np.dot(v, h), np.dot(h, light)
    a2 = roughness**4  # alpha = roughness^2
    d = a2 * (nh > 0) / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    vis = (hl > 0) * (vh > 0) / (2.0 * (abs(nv) * np.sqrt(a2 + (1 - a2) * nl * nl)
                                        + abs(nl) * np.sqrt(a2 + (1 - a2) * nv * nv)))  # fmt: skip
    if "anisotropy" in extras:
        (strength, rotation), alpha = extras["anisotropy"], roughness**2
        t0 = np.asarray(TANGENT[:3])
        b0 = np.cross(n, t0) * TANGENT[3]
        t = np.cos(rotation) * t0 + np.sin(rotation) * b0
        b = np.cross(n, t)
        at, ab = alpha * (1.0 - strength**2) + strength**2, alpha
        a2 = at * ab
        fv = np.array([ab * np.dot(t, h), at * np.dot(b, h), a2 * nh])
        w2 = a2 / np.dot(fv, fv)
        d = a2 * w2 * w2 / np.pi
        ggx_v = nl * np.linalg.norm([at * np.dot(t, v), ab * np.dot(b, v), nv])
        ggx_l = nv * np.linalg.norm([at * np.dot(t, light), ab * np.dot(b, light), nl])
        vis = 0.5 / (ggx_v + ggx_l)
    if ior == SPEC_GLOSS:
        f0 = np.asarray(specular_colour)
        fr = f0 + (1.0 - f0) * (1.0 - abs(vh)) ** 5
        c_diff = np.asarray(colour) * (1.0 - np.max(f0))
        return (1.0 - fr) * c_diff / np.pi + fr * vis * d
    f0 = np.minimum(((1.0 - ior) / (1.0 + ior)) ** 2 * np.asarray(specular_colour), 1.0)
    fr = f0 + (1.0 - f0) * (1.0 - abs(vh)) ** 5
    if "iridescence" in extras:
        factor, film_ior, thickness = extras["iridescence"]
        fr = (1.0 - factor) * fr + factor * f_iridescence(film_ior, abs(vh), thickness, f0)
    diffuse = np.asarray(colour) * (1.0 - dt) / np.pi
    return (1.0 - specular * np.max(fr)) * diffuse + specular * fr * vis * d


# CIE XYZ to linear Rec. 709, and the Gaussian fits of the colour matching functions in
# Fourier space (KHR_materials_iridescence's evalSensitivity).
XYZ_TO_REC709 = np.array(
    [
        [3.2404542, -1.5371385, -0.4985314],
        [-0.9692660, 1.8760108, 0.0415560],
        [0.0556434, -0.2040259, 1.0572252],
    ]
)


def sensitivity(opd: float, shift: np.ndarray) -> np.ndarray:
    phase = 2.0 * np.pi * opd * 1.0e-9
    val = np.array([5.4856e-13, 4.4201e-13, 5.2481e-13])
    pos = np.array([1.6810e06, 1.7953e06, 2.2084e06])
    var = np.array([4.3278e09, 9.3046e09, 6.6121e09])
    xyz = val * np.sqrt(2 * np.pi * var) * np.cos(pos * phase + shift) * np.exp(-(phase**2) * var)
    xyz[0] += (
        9.7470e-14
        * np.sqrt(2 * np.pi * 4.5282e09)
        * np.cos(2.2399e06 * phase + shift[0])
        * np.exp(-4.5282e09 * phase**2)
    )
    return XYZ_TO_REC709 @ (xyz / 1.0685e-7)


def f_iridescence(film_ior: float, cos1: float, thickness: float, base_f0) -> np.ndarray:
    """KHR_materials_iridescence's F_iridescence (its implementation notes) from air, with the
    paper's optical path difference 2 n d cos(theta2) (Belcour and Barla 2017, which the
    extension names as its model; its notes write cos(theta1)), base F0 guarded below 1 and
    the film's index blended to the outside's as the film thins to nothing (Khronos' sample
    viewer)."""

    def schlick(f0, c):
        return f0 + (1.0 - f0) * (1.0 - c) ** 5

    outside = 1.0
    t = min(1.0, max(0.0, thickness / 0.03))
    film = outside + (film_ior - outside) * t * t * (3.0 - 2.0 * t)
    sin2_sq = (outside / film) ** 2 * (1.0 - cos1**2)
    if sin2_sq >= 1.0:
        return np.ones(3)
    cos2 = np.sqrt(1.0 - sin2_sq)
    r12 = schlick(((film - outside) / (film + outside)) ** 2, cos1)
    t121 = 1.0 - r12
    phi12 = np.pi if film < outside else 0.0
    phi21 = np.pi - phi12
    f0 = np.clip(np.asarray(base_f0, dtype=np.float64), 0.0, 0.9999)
    base_ior = (1.0 + np.sqrt(f0)) / (1.0 - np.sqrt(f0))
    r23 = schlick(((base_ior - film) / (base_ior + film)) ** 2, cos2)
    phi = phi21 + np.where(base_ior < film, np.pi, 0.0)
    opd = 2.0 * film * thickness * cos2
    r123 = np.clip(r12 * r23, 1e-5, 0.9999)
    rs = t121**2 * r23 / (1.0 - r123)
    intensity = r12 + rs
    cm = rs - t121
    for m in (1, 2):
        cm = cm * np.sqrt(r123)
        intensity = intensity + cm * 2.0 * sensitivity(m * opd, m * phi)
    return np.maximum(intensity, 0.0)


def strip_pixels(image: np.ndarray) -> list[np.ndarray]:
    """The mean RGB of a block of pixels well inside each strip."""
    means = []
    for centre in STRIP_CENTRES:
        col = int((centre + XMAG) / (2 * XMAG) * WIDTH)
        means.append(image[HEIGHT // 2 - 3 : HEIGHT // 2 + 3, col - 3 : col + 3].reshape(-1, 3)
                     .mean(0))  # fmt: skip
    return means


# Per view elevation (normal, oblique, grazing), the light's (elevation, azimuth relative to
# the view's), degrees: on the view's side (retro and mirror directions), across and behind;
# and below the ground, where only the diffuse BTDF passes light.
LIGHTS = [(tl, phi) for tl in (10.0, 45.0, 80.0) for phi in (0.0, 90.0, 180.0)]
LIGHTS += [(tl, phi) for tl in (120.0, 165.0) for phi in (0.0, 90.0)]


@pytest.mark.parametrize("view_deg", [0.0, 35.0, 70.0])
def test_dielectric_brdf_is_the_specs_closed_form(
    tmp_path: Path, worker_binary: str, view_deg: float
) -> None:
    worst = 0.0
    compared = 0
    tv = view_deg
    for tl, phi in LIGHTS:
        view, light = direction(tv, 0.0), direction(tl, phi)
        scene = tmp_path / f"ground-{tv:g}-{tl:g}-{phi:g}.glb"
        ground_scene(scene, view, light)
        out = tmp_path / f"ground-{tv:g}-{tl:g}-{phi:g}.exr"
        subprocess.run([worker_binary, "render", str(scene), "-o", str(out), "--spp", "4",
                        "--width", str(WIDTH), "--height", str(HEIGHT), "--threads", "1",
                        "--max-depth", "2"],
                       check=True, capture_output=True, timeout=120)  # fmt: skip
        channels = read_exr(str(out))
        image = np.stack([channels["R"], channels["G"], channels["B"]], -1).astype(np.float64)
        for k, got in enumerate(strip_pixels(image)):
            want = INTENSITY * spec_brdf(*MATERIALS[k], v=view, light=light) * abs(light[1])
            where = f"material {k} {MATERIALS[k]}, view {tv} deg, light {tl} deg at {phi} deg"
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-7, err_msg=where)
            lit = want > 0.0
            if lit.any():
                worst = max(worst, float(np.max(np.abs(got[lit] / want[lit] - 1))))
            compared += 1
    assert compared == len(LIGHTS) * len(MATERIALS)
    print(f"view {view_deg} deg: worst relative difference {worst:.2e} over {compared}")
