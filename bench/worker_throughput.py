"""Worker render throughput: the C++ path tracer against Embree's raw ray rate.

Runs `renderfarm-worker bench` (worker/src/bench/bench.cpp), which renders the Cornell box, a
generated scene of at least 1M triangles and a generated scene of 144 Embree instances of one
mesh (both built in memory, never written to disk) at 1 and 2 threads, records the path
tracer's rays and replays them through bare rtcIntersect1 / rtcOccluded1 in the same process.
Prints samples/s, Mrays/s, the 1 -> 2 thread scaling and the ratio of the path tracer's ray
rate to the raw rate (targets: >= 0.6 and >= 1.8x), and writes
bench/results/worker_throughput.json.

Environment: RENDERFARM_WORKER (binary, default build/worker/renderfarm-worker),
BENCH_SPP / BENCH_SIZE / BENCH_THREADS to change the workload, BENCH_SCENES (a comma-separated
subset of cornell,mesh,instanced) to run only some of the scenes.

--mitsuba also times Mitsuba 3 (`llvm_ad_rgb` unless --mitsuba-variant; .venv-mitsuba:
scripts/install-deps.sh --mitsuba) against the worker on the Cornell box at #38's settings
(256x256, 8 bounces, 256 spp, both on every core: the worker's `render --threads` = the CPU
count): Mitsuba through bench/support/mitsuba_render.py (the same glTF read into Mitsuba meshes,
`principled` BSDFs, `path` integrator, independent sampler), --mitsuba-renders renders each,
each side's median seconds of sampling (Mitsuba's first render, which compiles its kernels, left
out; the worker's own figure, which leaves out loading the scene), samples/s and the ratio, and
which of AVX-512 and AVX2 the CPU has (the worker's own code is built for x86-64-v2). --isa
native compares both at the widest instruction set the CPU has (the worker with
RENDERFARM_ISA=native: Embree and its sampler's kernels uncapped; Mitsuba's JIT and Embree as
they are); --isa avx2 both capped at AVX2, as on a CPU without AVX-512 (the worker at its
default, RENDERFARM_ISA=avx2; Mitsuba's Dr.Jit compiling for `haswell` with 8-wide vectors and
its bundled Embree capped through bench/support/embree_isa_shim.c, preloaded); --isa both (the
default) runs each where the CPU has AVX-512. The figures go under "mitsuba" in the JSON, by ISA.

    .venv/bin/python bench/worker_throughput.py [--mitsuba] [--mitsuba-only]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TARGET_RATIO = 0.6
TARGET_SCALING = 1.8


# #38's comparison with Mitsuba: the Cornell box at 256x256, 8 bounces, 256 spp.
MITSUBA_SIZE, MITSUBA_DEPTH, MITSUBA_SPP = 256, 8, 256
WORKER_LINE = re.compile(r"wrote .* in ([0-9.]+) s: ([0-9.]+) samples/s")


def cpu_vectors() -> dict:
    flags = set()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[1].split())
            break
    return {"avx512f": "avx512f" in flags, "avx2": "avx2" in flags}


def build_embree_shim(tmp: str) -> Path:
    """bench/support/embree_isa_shim.c compiled into tmp (cc)."""
    out = Path(tmp) / "embree_isa_shim.so"
    source = ROOT / "bench" / "support" / "embree_isa_shim.c"
    subprocess.run(["cc", "-O2", "-shared", "-fPIC", "-o", str(out), str(source), "-ldl"],
                   check=True)  # fmt: skip
    return out


def compare_mitsuba(binary: Path, python: Path, variant: str, renders: int, isa: str) -> dict:
    """The worker and Mitsuba on the Cornell box at #38's settings, both at instruction set
    `isa` (native or avx2): median sampling seconds."""
    if not python.exists():
        sys.exit(f"no Mitsuba Python at {python} (scripts/install-deps.sh --mitsuba)")
    scene = ROOT / "examples" / "cornell-box.gltf"
    threads = os.cpu_count() or 1
    worker_s, worker_rate = [], []
    worker_env = dict(os.environ, RENDERFARM_ISA=isa)
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(renders):
            proc = subprocess.run(
                [str(binary), "render", str(scene), "-o", f"{tmp}/worker.exr",
                 "--spp", str(MITSUBA_SPP), "--width", str(MITSUBA_SIZE),
                 "--height", str(MITSUBA_SIZE), "--max-depth", str(MITSUBA_DEPTH),
                 "--threads", str(threads), "--seed", str(k)],
                capture_output=True, text=True, check=True, env=worker_env)  # fmt: skip
            match = WORKER_LINE.search(proc.stderr)
            if not match:
                sys.exit(f"no timing in the worker's output:\n{proc.stderr}")
            worker_s.append(float(match.group(1)))
            worker_rate.append(float(match.group(2)))
        config = Path(tmp) / "mitsuba.json"
        config.write_text(json.dumps({
            "scene": str(scene), "width": MITSUBA_SIZE, "height": MITSUBA_SIZE,
            "spp": MITSUBA_SPP, "max_depth": MITSUBA_DEPTH, "variant": variant,
            "renders": renders + 1, "isa": isa}))  # fmt: skip
        mitsuba_env = dict(os.environ)
        if isa == "avx2":
            mitsuba_env.update(LD_PRELOAD=str(build_embree_shim(tmp)), EMBREE_MAX_ISA="avx2")
        proc = subprocess.run(
            [str(python), str(ROOT / "bench" / "support" / "mitsuba_render.py"), str(config)],
            capture_output=True, text=True, errors="replace", env=mitsuba_env)  # fmt: skip
        found = re.search(r"^RESULT (.*)$", proc.stdout, re.M)
        if proc.returncode != 0 or not found:
            sys.exit(f"Mitsuba failed (exit {proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
        if isa == "avx2" and "max_isa=avx2" not in proc.stderr:
            sys.exit(f"Mitsuba's Embree was not capped (no embree_isa_shim line):\n{proc.stderr}")
        result = json.loads(found.group(1))
    samples = MITSUBA_SIZE * MITSUBA_SIZE * MITSUBA_SPP
    mitsuba_s = statistics.median(result["seconds"][1:])
    w_s = statistics.median(worker_s)
    figures = {
        "settings": {"size": MITSUBA_SIZE, "bounces": MITSUBA_DEPTH, "spp": MITSUBA_SPP,
                     "threads": threads, "variant": variant, "renders": renders, "isa": isa,
                     "mitsuba_llvm_target": result.get("llvm_target") or "native"},
        "cpu": cpu_vectors(),
        "worker_seconds": worker_s,
        "mitsuba_seconds": result["seconds"],
        "mitsuba_first_render_s": result["seconds"][0],
        "worker_samples_per_s": samples / w_s,
        "mitsuba_samples_per_s": samples / mitsuba_s,
        "worker_over_mitsuba": (samples / w_s) / (samples / mitsuba_s),
    }  # fmt: skip
    cpu = ", ".join(k for k, v in figures["cpu"].items() if v) or "neither AVX2 nor AVX-512"
    print(f"Cornell box {MITSUBA_SIZE}x{MITSUBA_SIZE}, {MITSUBA_DEPTH} bounces, {MITSUBA_SPP} spp, "
          f"{threads} threads ({cpu}; both at {isa}): "
          f"worker {w_s:.2f} s ({samples / w_s:,.0f} samples/s), "
          f"Mitsuba {variant} {mitsuba_s:.2f} s ({samples / mitsuba_s:,.0f} samples/s; its first "
          f"render {result['seconds'][0]:.2f} s with the JIT): worker / Mitsuba "
          f"{figures['worker_over_mitsuba']:.2f}")  # fmt: skip
    return figures


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument(
        "--mitsuba",
        action="store_true",
        help="also time Mitsuba 3 on the Cornell box (#38's settings)",
    )
    parser.add_argument(
        "--mitsuba-only",
        action="store_true",
        help="only the Mitsuba comparison (not the Embree replay)",
    )
    parser.add_argument(
        "--mitsuba-python", type=Path, default=ROOT / ".venv-mitsuba" / "bin" / "python"
    )
    parser.add_argument("--mitsuba-variant", default="llvm_ad_rgb")
    parser.add_argument("--mitsuba-renders", type=int, default=3)
    parser.add_argument(
        "--isa",
        choices=["native", "avx2", "both"],
        default="both",
        help="the instruction set of the Mitsuba comparison (both: native and, on a CPU with "
        "AVX-512, avx2)",
    )
    args = parser.parse_args()
    isas = [args.isa] if args.isa != "both" else ["native"]
    if args.isa == "both" and cpu_vectors()["avx512f"]:
        isas.append("avx2")

    def mitsuba() -> dict:
        return {isa: compare_mitsuba(binary, args.mitsuba_python, args.mitsuba_variant,
                                     args.mitsuba_renders, isa) for isa in isas}  # fmt: skip

    binary = Path(os.environ.get("RENDERFARM_WORKER", ROOT / "build/worker/renderfarm-worker"))
    if not binary.exists():
        sys.exit(f"{binary} not found: build the worker first (make worker)")
    out = ROOT / "bench" / "results" / "worker_throughput.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.mitsuba_only:
        doc = {"mitsuba": mitsuba()}
        out.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {out.relative_to(ROOT)}")
        return doc
    size = os.environ.get("BENCH_SIZE", "192")
    cmd = [
        str(binary),
        "bench",
        "--cornell",
        str(ROOT / "examples" / "cornell-box.gltf"),
        "--json",
        str(out),
        "--width",
        size,
        "--height",
        size,
        "--spp",
        os.environ.get("BENCH_SPP", "32"),
        "--threads",
        os.environ.get("BENCH_THREADS", "1,2"),
        "--scenes",
        os.environ.get("BENCH_SCENES", "cornell,mesh,instanced"),
    ]
    subprocess.run(cmd, check=True)
    doc = json.loads(out.read_text())
    summary = {}
    for scene in doc["scenes"]:
        by_threads = scene["threads"]
        counts = sorted(by_threads, key=int)
        ratios = [by_threads[t]["ray_rate_vs_raw"] for t in counts]
        scaling = by_threads[counts[-1]].get("scaling_vs_first")
        summary[scene["scene"]] = {"min_ratio": min(ratios), "scaling": scaling}
        verdict_ratio = "meets" if min(ratios) >= TARGET_RATIO else "below"
        line = (
            f"{scene['scene']:10} {scene['triangles']:>9,} triangles: ray rate "
            f"{min(ratios):.2f}-{max(ratios):.2f} of raw Embree ({verdict_ratio} {TARGET_RATIO})"
        )
        if scaling is not None:
            verdict_scaling = "meets" if scaling >= TARGET_SCALING else "below"
            line += f", scaling {scaling:.2f}x ({verdict_scaling} {TARGET_SCALING}x)"
        print(line)
    doc["summary"] = summary
    if args.mitsuba:
        doc["mitsuba"] = mitsuba()
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out.relative_to(ROOT)}")
    return doc


if __name__ == "__main__":
    main()
