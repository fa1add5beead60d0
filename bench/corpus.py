"""A real-world glTF corpus through the farm's loader and renderer (#37).

    .venv/bin/python bench/corpus.py DIR [--worker PATH] [--size 128] [--spp 16] [--threads 2]
        [--timeout 300] [--json OUT.json] [--markdown] [--only SUBSTRING]

DIR holds downloaded models (none are in the repository): every .gltf/.glb under it is a scene.
A model folder in the Khronos layout (MODEL/glTF, MODEL/glTF-Binary, MODEL/glTF-Draco, ...)
gives one row for its plain form (glTF, else glTF-Binary, else glTF-Embedded) and one row per
other variant (Draco, KTX2/Basis, quantized, meshopt, ...); any other .gltf/.glb is a row of its
own. The source is the first folder under DIR, the licence is read from the model folder
(metadata.json, LICENSE.md, licence.txt/license.txt or README.md).

Each scene goes the way a submission goes: a .gltf is packed into one GLB with its buffers and
images as `renderfarm submit` does (renderfarm.domain.scenes.pack.pack_gltf), then
`renderfarm-worker inspect --json` (the farm's acceptance: the workers' loader within the
limits) and `renderfarm-worker render` under an environment map (a generated gradient sky with
a sun, bench/support/sky_scene.py) at SIZE x SIZE and SPP samples per pixel; a scene with
animations is rendered posed at --time 0 (a farm job's frame 0), which also reads its
animations. Each step has a timeout (the process group is killed): nothing hangs.

Per scene: accepted (or the refusal's message), the loader's warnings from both runs, each
classified as expected (occlusionTexture: a path tracer computes occlusion), dropped (a feature
the renderer ignores: an unsupported extension, a skipped primitive, a texture not read),
approximated (a feature rendered otherwise than specified: a KTX2 texture's fallback image,
a light's range, an unsupported IOR) or other (information: no camera, degenerate triangles,
a factor clamped from a rounding error); the render's own time (stats-json render_s, and the
load), and the non-finite pixels of the EXR (OpenImageIO) and the non-finite samples the
worker recorded as 0. Prints a table, writes bench/results/corpus.json (or --json), and with
--markdown prints the table for docs/scenes.md ("Real-world corpus").
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from support.results import write_results  # noqa: E402
from support.sky_scene import sky  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PLAIN = ("glTF", "glTF-Binary", "glTF-Embedded")  # one row per model, in this order of choice
SKIP_VARIANTS = {"glTF-IBL"}  # Khronos' image-based-lighting copies of a plain variant

# (class, pattern, feature label): the loader's warnings (worker/src/scene/gltf_loader.cpp,
# scene.cpp); the first that matches classifies a warning. {0} in a label is the first group.
RULES: list[tuple[str, str, str]] = [
    ("expected", r"occlusionTexture is ignored", "occlusionTexture"),
    # Extensions that do not change the image: metadata, and a triangulation hint for importers.
    ("other", r"extension '(KHR_xmp|KHR_xmp_json_ld|FB_ngon_encoding)' is not supported", "{0}"),
    ("approximated", r"KHR_texture_basisu is not decoded", "KHR_texture_basisu (fallback image)"),
    ("dropped", r"material extension '([^']+)' is not supported", "{0}"),
    ("dropped", r"extension '([^']+)' is not supported; ignoring", "{0}"),
    ("dropped", r"extension '([^']+)' is not supported; using 'source'", "{0}"),
    ("dropped", r"'([^']+)' is not translation, rotation, scale or weights", "animation path {0}"),
    ("dropped", r"has no mesh with morph targets; weights channel ignored", "weights channel"),
    ("dropped", r"missing image; texture ignored", "texture without image"),
    ("dropped", r"could not be loaded \(uri", "texture image unreadable"),
    ("dropped", r"unknown type '([^']+)'; light ignored", "light type {0}"),
    ("dropped", r"has a skin but the primitive no JOINTS_0", "skin without joints"),
    ("dropped", r": (?:.*) ignored: ", "texture not decoded"),
    ("approximated", r"'range' is ignored", "KHR_lights_punctual range"),
    (
        "approximated",
        r"KHR_materials_ior\.ior .* is not supported",
        "KHR_materials_ior out of range",
    ),
    (
        "approximated",
        r"TANGENT of a skinned or morphed mesh is not used",
        "TANGENT of deformed mesh",
    ),
    ("approximated", r"clearcoatNormalTexture uses another TEXCOORD", "clearcoat normal TEXCOORD"),
    ("other", r"no camera in the scene", "no camera"),
    ("other", r"degenerate triangle", "degenerate triangles"),
    ("other", r"is outside \[0, 1\]; clamped", "factor clamped"),
    ("other", r"index count is not a multiple of 3", "trailing indices"),
    ("other", r"KHR_materials_unlit excludes clearcoat and sheen", "unlit with layers"),
]


def classify(warning: str) -> tuple[str, str]:
    """(class, feature) of one loader warning; unknown ones are 'other' under their own text."""
    for kind, pattern, label in RULES:
        m = re.search(pattern, warning)
        if m:
            return kind, label.format(*m.groups()) if m.groups() else label
    return "other", warning.split(": ", 1)[-1][:60]


def find_scenes(root: Path) -> list[dict]:
    """One entry per row: {path, source, model, variant, licence}, sorted by source and model."""
    by_model: dict[tuple[Path, str], dict[str, list[Path]]] = {}
    for path in sorted(root.rglob("*")):
        if path.suffix.lower() not in (".gltf", ".glb") or not path.is_file():
            continue
        parent = path.parent
        if parent.name.startswith("glTF") and parent != root:  # MODEL/glTF-Variant/scene.gltf
            key, variant = (parent.parent, parent.parent.name), parent.name
        else:  # a scene file of its own; several in a folder are several models
            key, variant = (parent, path.stem), path.suffix[1:].lower()
        by_model.setdefault(key, {}).setdefault(variant, []).append(path)
    rows = []
    for (folder, name), variants in by_model.items():
        source = folder.relative_to(root).parts[0] if folder != root else root.name
        model = name if name not in ("scene", "model") else folder.name
        plain = [v for v in PLAIN if v in variants]
        chosen = plain[:1] + [
            v for v in sorted(variants) if v not in PLAIN and v not in SKIP_VARIANTS
        ]
        for variant in chosen:
            rows.append(
                {
                    "path": str(variants[variant][0]),
                    "source": source,
                    "model": model,
                    "variant": variant,
                    "licence": licence(folder),
                }
            )
    return sorted(rows, key=lambda r: (r["source"], r["model"].lower(), r["variant"]))


LICENCE_URLS = [
    (r"licenses/by-nc-sa/", "CC-BY-NC-SA-4.0"),
    (r"licenses/by-nc/", "CC-BY-NC-4.0"),
    (r"licenses/by-sa/", "CC-BY-SA-4.0"),
    (r"licenses/by/4", "CC-BY-4.0"),
    (r"licenses/by/3", "CC-BY-3.0"),
    (r"publicdomain/zero", "CC0-1.0"),
    (r"\bCC[- ]BY[- ]4", "CC-BY-4.0"),
    (r"\bCC0\b", "CC0-1.0"),
]


def licence(folder: Path) -> str:
    """The model's licence as its folder states it (SPDX identifiers where given)."""
    meta = folder / "metadata.json"
    if meta.is_file():
        try:
            legal = json.loads(meta.read_text()).get("legal", [])
            names = [x.get("spdx") or x.get("license") for x in legal]
            if any(names):
                return ", ".join(dict.fromkeys(n for n in names if n))
        except (ValueError, AttributeError):
            pass
    for name in ("LICENSE.md", "licence.txt", "license.txt", "LICENSE", "README.md"):
        f = folder / name
        if not f.is_file():
            continue
        text = f.read_text(errors="replace")
        m = re.search(r'SPDX license identifier: "([^"]+)"', text)
        if m:
            return m.group(1)
        m = re.search(r"license type:\s*(.*)", text, re.I)
        line = m.group(1) if m else text
        for pattern, spdx in LICENCE_URLS:
            if re.search(pattern, line, re.I):
                return spdx
        if m:
            return m.group(1).split()[0]
    return "not stated"


def gltf_json(data: bytes) -> dict:
    """The JSON of a GLB or .gltf's bytes ({} if it cannot be read)."""
    try:
        if data[:4] == b"glTF":
            length = struct.unpack_from("<I", data, 12)[0]
            return json.loads(data[20 : 20 + length])
        return json.loads(data)
    except (ValueError, struct.error):
        return {}


def run(cmd: list[str], timeout: float) -> tuple[int | None, str, str, float]:
    """(exit status or None on timeout, stdout, stderr, wall seconds); on a timeout the whole
    process group is killed, so nothing outlives it."""
    t0 = time.monotonic()
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        out, err = proc.communicate(timeout=timeout)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        code = None
    return code, out, err, time.monotonic() - t0


def nonfinite_pixels(exr: Path) -> int:
    import OpenImageIO as oiio

    pixels = oiio.ImageInput.open(str(exr))
    if pixels is None:
        raise RuntimeError(f"cannot read {exr}: {oiio.geterror()}")
    data = pixels.read_image(oiio.FLOAT)
    pixels.close()
    return int((~np.isfinite(np.asarray(data))).any(axis=-1).sum())


def write_sky(path: Path) -> None:
    import OpenImageIO as oiio

    pixels = sky()
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.FLOAT))
    out.write_image(pixels)
    out.close()


def measure(row: dict, args: argparse.Namespace, tmp: Path, env_map: Path) -> dict:
    """Pack, inspect and render one scene; returns the row with its figures."""
    from renderfarm.domain.scenes.pack import pack_gltf
    from renderfarm.errors import SceneError

    result = dict(row, accepted=False, error="", warnings=[], render_s=None, load_s=None,
                  wall_s=None, nonfinite_pixels=None, nonfinite_samples=0, time=None)  # fmt: skip
    scene = Path(row["path"])
    try:
        glb = pack_gltf(scene)
    except SceneError as e:  # refused by the client's packing or the server's checks
        result["error"] = f"pack: {e}"
        return result
    packed = tmp / "scene.glb"
    packed.write_bytes(glb)
    doc = gltf_json(glb)
    result["extensions"] = sorted(doc.get("extensionsUsed", []))
    result["animations"] = len(doc.get("animations", []))
    warnings: list[str] = []
    code, out, err, _ = run(
        [args.worker, "inspect", str(packed), "--json", "--name", scene.name], args.timeout
    )
    if code is None:
        result["error"] = f"inspect: timed out after {args.timeout:.0f} s"
        return result
    try:
        answer = json.loads(out.strip().splitlines()[-1])
    except (ValueError, IndexError):
        answer = {"ok": False, "error": f"inspect exited {code}: {err.strip()[-300:]}"}
    warnings += answer.get("warnings", [])
    if not answer.get("ok"):
        result["error"] = answer.get("error", "").strip()
        result["warnings"] = warnings
        return result
    result["triangles"] = answer.get("instanced_triangles")
    exr, stats = tmp / "out.exr", tmp / "stats.json"
    exr.unlink(missing_ok=True)
    stats.unlink(missing_ok=True)
    cmd = [args.worker, "render", str(packed), "-o", str(exr), "--spp", str(args.spp),
           "--width", str(args.size), "--height", str(args.size), "--threads", str(args.threads),
           "--environment", str(env_map), "--stats-json", str(stats)]  # fmt: skip
    if result["animations"]:
        cmd += ["--time", "0"]
        result["time"] = 0.0
    code, _, err, wall = run(cmd, args.timeout)
    result["wall_s"] = wall
    for line in err.splitlines():
        message = line[9:].replace(f"{packed}: ", f"{scene.name}: ", 1)
        if line.startswith("warning: ") and message not in warnings:
            warnings.append(message)
    result["warnings"] = warnings
    if code != 0:
        last = [ln for ln in err.splitlines() if ln.startswith("error: ")]
        why = last[-1][7:] if last else err.strip()[-300:]
        result["error"] = (
            f"render: timed out after {args.timeout:.0f} s" if code is None else f"render: {why}"
        )
        return result
    result["accepted"] = True
    m = re.search(r"\((\d+) non-finite samples recorded as 0\)", err)
    result["nonfinite_samples"] = int(m.group(1)) if m else 0
    try:
        figures = json.loads(stats.read_text())
        result["load_s"] = figures["load_s"]
        result["render_s"] = sum(f["render_s"] + f["update_s"] for f in figures["frames"])
    except (OSError, ValueError, KeyError):
        pass
    result["nonfinite_pixels"] = nonfinite_pixels(exr)
    return result


def summarize(row: dict) -> dict:
    """Adds per-class feature lists to a measured row."""
    classes: dict[str, list[str]] = {"expected": [], "dropped": [], "approximated": [], "other": []}
    for w in row["warnings"]:
        kind, feature = classify(w)
        if feature not in classes[kind]:
            classes[kind].append(feature)
    row["classified"] = classes
    return row


def seconds(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def notes(row: dict) -> str:
    """The row's warnings column: refusal, dropped and approximated features, then others."""
    c = row["classified"]
    parts = []
    if not row["accepted"]:
        error = " ".join(row["error"].split())
        parts.append("**refused**: " + (error if len(error) <= 200 else error[:197] + "..."))
    parts += [f"dropped: {f}" for f in c["dropped"]]
    parts += [f"approx.: {f}" for f in c["approximated"]]
    parts += [f for f in c["other"] if f != "no camera"]  # counted in the summary line
    return "; ".join(parts).replace("|", "\\|") or "-"


def nonfinite(row: dict) -> str:
    if not row["accepted"]:
        return "-"
    text = str(row["nonfinite_pixels"])
    return text + (f" ({row['nonfinite_samples']} samples)" if row["nonfinite_samples"] else "")


def model_name(row: dict) -> str:
    variant = row["variant"]
    return row["model"] + (f" ({variant})" if variant not in PLAIN + ("gltf", "glb") else "")


def totals(rows: list[dict]) -> dict:
    dropped: Counter = Counter()
    approximated: Counter = Counter()
    for r in rows:
        dropped.update(r["classified"]["dropped"])
        approximated.update(r["classified"]["approximated"])
    return {
        "scenes": len(rows),
        "models": len({(r["source"], r["model"]) for r in rows}),
        "accepted": sum(r["accepted"] for r in rows),
        "with_dropped_feature": sum(bool(r["classified"]["dropped"]) for r in rows),
        "with_approximated_feature": sum(bool(r["classified"]["approximated"]) for r in rows),
        "with_nonfinite_pixels": sum(bool(r["nonfinite_pixels"]) for r in rows),
        "with_nonfinite_samples": sum(bool(r["nonfinite_samples"]) for r in rows),
        "without_camera": sum("no camera" in r["classified"]["other"] for r in rows),
        "dropped": dict(dropped.most_common()),
        "approximated": dict(approximated.most_common()),
    }


def summary_line(t: dict) -> str:
    def listed(counts: dict) -> str:
        return ", ".join(f"{k} ({v})" for k, v in counts.items()) or "none"

    return (
        f"{t['scenes']} scenes of {t['models']} models, {t['accepted']} accepted; "
        f"{t['with_dropped_feature']} with a dropped feature: {listed(t['dropped'])}; "
        f"{t['with_approximated_feature']} with an approximated one: "
        f"{listed(t['approximated'])}; {t['with_nonfinite_pixels']} with non-finite pixels, "
        f"{t['with_nonfinite_samples']} with non-finite samples recorded as 0; "
        f"{t['without_camera']} without a camera (framed from +Z)."
    )


def markdown(rows: list[dict], t: dict) -> str:
    lines = [
        summary_line(t),
        "",
        "| model | source | licence | accepted | warnings (dropped, approximated, other) "
        "| load + render s | non-finite px |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        total = None if r["render_s"] is None else (r["load_s"] or 0) + r["render_s"]
        lines.append(
            f"| {model_name(r)} | {r['source']} | {r['licence']} | "
            f"{'yes' if r['accepted'] else 'no'} | {notes(r)} | {seconds(total)} | "
            f"{nonfinite(r)} |"
        )
    return "\n".join(lines)


def print_table(rows: list[dict]) -> None:
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        for r in rows:
            print(f"{model_name(r):40} {r['source']:14} {'yes' if r['accepted'] else 'NO':3} "
                  f"{seconds(r['render_s']):>6} {nonfinite(r):>4}  {notes(r)}")  # fmt: skip
        return
    table = Table("model", "source", "licence", "ok", "load s", "render s", "non-finite", "notes")
    for r in rows:
        ok = "yes" if r["accepted"] else "NO"
        cells = (seconds(r["load_s"]), seconds(r["render_s"]), nonfinite(r), notes(r))
        table.add_row(model_name(r), r["source"], r["licence"], ok, *cells)
    Console(width=200).print(table)


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", type=Path, help="folder of downloaded .gltf/.glb models")
    parser.add_argument("--worker", default=os.environ.get("RENDERFARM_WORKER",
                        str(ROOT / "build/worker/renderfarm-worker")))  # fmt: skip
    parser.add_argument("--size", type=int, default=128, help="image width and height")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=300, help="seconds per step and scene")
    parser.add_argument("--json", type=Path, help="write the figures here (default "
                        "bench/results/corpus.json)")  # fmt: skip
    parser.add_argument("--markdown", action="store_true", help="print the docs' table")
    parser.add_argument("--only", default="", help="only scenes whose path contains this")
    args = parser.parse_args()
    if not Path(args.worker).is_file():
        sys.exit(f"{args.worker} not found: build the worker first (make worker)")
    scenes = [s for s in find_scenes(args.dir.resolve()) if args.only in s["path"]]
    if not scenes:
        sys.exit(f"no .gltf or .glb under {args.dir}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="rf-corpus-") as tmp_name:
        tmp = Path(tmp_name)
        env_map = tmp / "sky.hdr"
        write_sky(env_map)
        for i, scene in enumerate(scenes, 1):
            row = summarize(measure(scene, args, tmp, env_map))
            rows.append(row)
            state = "ok" if row["accepted"] else "REFUSED " + row["error"][:120]
            print(f"[{i}/{len(scenes)}] {row['source']}/{model_name(row)}: {state}, "
                  f"{seconds(row['render_s'])} s, {len(row['warnings'])} warning(s)",
                  file=sys.stderr, flush=True)  # fmt: skip
    t = totals(rows)
    print_table(rows)
    print(summary_line(t))
    slowest = sorted((r for r in rows if r["render_s"] is not None),
                     key=lambda r: -r["render_s"])[:5]  # fmt: skip
    print("slowest: " + ", ".join(f"{model_name(r)} {r['render_s']:.1f} s" for r in slowest))
    figures = {
        "benchmark": "corpus",
        "date": datetime.date.today().isoformat(),
        "command": " ".join(["bench/corpus.py", *sys.argv[1:]]),
        "size": args.size,
        "spp": args.spp,
        "threads": args.threads,
        "totals": t,
        "scenes": rows,
    }
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
        out = args.json
    else:
        out = write_results("corpus", figures)
    print(f"wrote {out}")
    if args.markdown:
        print()
        print(markdown(rows, t))
    return figures


if __name__ == "__main__":
    main()
