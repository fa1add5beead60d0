"""The server image's file layout, built without Docker, serves the dashboard and the API docs.

deploy/docker/server.Dockerfile is read stage by stage and reproduced in a temporary directory
per stage (its file system root): COPY instructions copy from the repository (through the
image's .dockerignore) or from an earlier stage, and RUN steps run. The web stage's steps run as
they are (npm ci from the npm registry's cache or the registry, npm run build). In the build
stage, the steps that would download or install system-wide are replaced by their offline
equivalents, each named in _reproduce_build_step: the apt set-up is the one this machine already
has from the same script (`make test-deploy` depends on `make build`), `make proto` runs with
the .venv's Python, and `--server-venv DIR` becomes a new virtual environment DIR in which the
server package is installed not editable from a wheel of the build context, its dependencies
coming from the .venv's site-packages (a .pth file) instead of being downloaded again. The
image's entrypoint then runs from that environment on loopback, and / must be the built
dashboard (with its sign-in), /docs and /redoc must reference only assets the server serves.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import httpx
import pytest

from renderfarm.cli.localfarm import free_port
from renderfarm.infra.worker_binary import find_worker_binary

from .conftest import ROOT
from .waiting import wait_until

DOCKERFILE = ROOT / "deploy" / "docker" / "server.Dockerfile"
IGNORE = ROOT / "deploy" / "docker" / "server.Dockerfile.dockerignore"
ADMIN_TOKEN = "image-test-admin-0123"


def _instructions(dockerfile: Path) -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", dockerfile.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def _stages(dockerfile: Path) -> list[tuple[str, list[tuple[str, str]]]]:
    """(name, instructions) of each stage; an unnamed stage is named by its index."""
    stages: list[tuple[str, list[tuple[str, str]]]] = []
    for op, rest in _instructions(dockerfile):
        if op == "FROM":
            words = rest.split()
            name = words[-1] if len(words) >= 3 and words[-2].upper() == "AS" else str(len(stages))
            stages.append((name, []))
        elif stages:
            stages[-1][1].append((op, rest))
    return stages


# ------------------------------------------------------------------------- .dockerignore
def _pattern_regex(pattern: str) -> re.Pattern:
    """A .dockerignore pattern (Go filepath.Match plus `**`) as a regular expression."""
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pattern[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pattern[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(pattern[i]), i + 1
    return re.compile(out)


def _ignore_rules() -> list[tuple[bool, re.Pattern]]:
    rules = []
    for line in IGNORE.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            keep = line.startswith("!")
            rules.append((keep, _pattern_regex(line.lstrip("!").strip("/"))))
    return rules


def _excluded(rel: str, rules) -> bool:
    """Docker's rule: the last pattern that matches the path or one of its parents decides."""
    parts = rel.split("/")
    prefixes = ["/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    excluded = False
    for keep, regex in rules:
        if any(regex.fullmatch(p) for p in prefixes):
            excluded = not keep
    return excluded


def _copy_from_context(src: str, dest: Path, rules) -> None:
    source = ROOT / src
    assert source.exists(), f"COPY {src}: not in the repository"
    if source.is_file():
        assert not _excluded(src, rules), f"COPY {src}: excluded by {IGNORE.name}"
        target = dest / source.name if dest.is_dir() else dest
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source, target)
        return
    copied = 0
    for path in sorted(source.rglob("*")):
        rel = path.relative_to(ROOT).as_posix()
        if path.is_dir() or _excluded(rel, rules):
            continue
        target = dest / path.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, target)
        copied += 1
    assert copied, f"COPY {src}: every file is excluded by {IGNORE.name}"


# ------------------------------------------------------------------------ the stages
def _run(args, cwd: Path, env: dict | None = None, timeout: float = 300) -> str:
    done = subprocess.run(
        args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )
    assert done.returncode == 0, f"{args} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout


def _reproduce_build_step(step: str, workdir: Path, root: Path) -> None:
    """One `&&` step of the build stage's RUN, without Docker and without downloads."""
    python = sys.executable
    if step in ("scripts/install-deps.sh", "scripts/install-deps.sh --apt-only"):
        # The apt packages and the .venv: this machine was set up by the same script.
        return
    if step == "make proto":
        # The Makefile's own recipe, with the .venv's Python (its `deps` prerequisite is the
        # set-up above).
        _run(["make", "-s", "-o", "deps", "proto", f"PY={python}"], cwd=workdir)
        return
    m = re.fullmatch(r"scripts/install-deps\.sh --server-venv (/\S+)", step)
    if m:
        venv = root / m.group(1).lstrip("/")
        stubs = list((workdir / "server" / "renderfarm" / "v1").glob("*_pb2.py"))
        assert stubs, "--server-venv needs the gRPC stubs (make proto)"
        _run([python, "-m", "venv", "--without-pip", str(venv)], cwd=workdir)
        # The dependencies pip would download into the image: the .venv's installed copies.
        site = Path(_run([str(venv / "bin" / "python"), "-c",
                          "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         cwd=workdir).strip())  # fmt: skip
        (site / "_image_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
        wheels = workdir / "wheels"
        _run(
            [python, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
             "--no-index", "-w", str(wheels), "./server"],
            cwd=workdir,
        )  # fmt: skip
        _run(
            [python, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q",
             "--no-deps", "--no-index", *map(str, wheels.glob("renderfarm-*.whl"))],
            cwd=workdir,
        )  # fmt: skip
        return
    if step.startswith(("find /opt/", "rm -rf /opt/")):
        _run(["bash", "-c", step.replace(" /opt/", f" {root}/opt/")], cwd=workdir)
        return
    pytest.fail(f"the build stage's step {step!r} has no reproduction here: add one")


MAKEFILE_WORKER_CONFIGURE = "cmake -S worker -B $(BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release"


def _reproduce_worker_step(step: str, workdir: Path) -> None:
    """One step of the worker stage: the checkout's binary, which `make worker` configured
    with the same CMake command, stands in for the build."""
    binary = workdir / "build" / "worker" / "renderfarm-worker"
    if step == "scripts/install-deps.sh --apt-only":
        return
    if step.startswith("cmake -S "):
        # The image configures the worker exactly as the Makefile does.
        assert step.split(" \\")[0].strip() == MAKEFILE_WORKER_CONFIGURE.replace(
            "$(BUILD)", "build/worker"
        ), step
        assert MAKEFILE_WORKER_CONFIGURE in (ROOT / "Makefile").read_text()
        return
    if step.startswith("cmake --build "):
        binary.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(find_worker_binary(), binary)
        return
    if step.startswith("strip "):
        _run(["strip", "-o", str(binary), str(binary)], cwd=workdir)
        return
    if step == "build/worker/renderfarm-worker --version":
        _run([str(binary), "--version"], cwd=workdir)
        return
    pytest.fail(f"the worker stage's step {step!r} has no reproduction here: add one")


def _build_stage(name: str, instructions, roots: dict[str, Path], base: Path, rules) -> None:
    root = roots[name] = base / name
    workdir = root
    for op, rest in instructions:
        if op == "WORKDIR":
            workdir = root / rest.lstrip("/")
            workdir.mkdir(parents=True, exist_ok=True)
        elif op == "COPY":
            words = rest.split()
            frm = next((w.split("=", 1)[1] for w in words if w.startswith("--from=")), None)
            src, dest = [w for w in words if not w.startswith("--")]
            target = root / dest.lstrip("/") if dest.startswith("/") else workdir / dest
            if dest.endswith("/"):
                target.mkdir(parents=True, exist_ok=True)
            if frm is None:
                _copy_from_context(src, target, rules)
            else:
                assert frm in roots, f"COPY --from={frm}: no earlier stage of that name"
                source = roots[frm] / src.lstrip("/")
                assert source.is_dir(), f"COPY --from={frm} {src}: the stage did not make it"
                shutil.copytree(source, target, dirs_exist_ok=True)
        elif op == "RUN" and name == "web":
            # Run as it is: the same commands as the Makefile's `web` target.
            _run(["sh", "-c", rest], cwd=workdir, timeout=600)
        elif op == "RUN" and name == "worker":
            for step in (s.strip() for s in rest.split("&&")):
                _reproduce_worker_step(step, workdir)
        elif op == "RUN" and name == "build":
            for step in (s.strip() for s in rest.split("&&")):
                _reproduce_build_step(step, workdir, root)


@pytest.fixture(scope="module")
def image(tmp_path_factory) -> dict:
    """The web and build stages reproduced; what the final stage runs, and how."""
    stages = _stages(DOCKERFILE)
    names = [name for name, _ in stages]
    assert names[:3] == ["web", "worker", "build"], names
    base = tmp_path_factory.mktemp("image")
    rules = _ignore_rules()
    roots: dict[str, Path] = {}
    for name, instructions in stages[:-1]:
        _build_stage(name, instructions, roots, base, rules)
    final = stages[-1][1]
    copies = [rest for op, rest in final if op == "COPY" and rest.startswith("--from=")]
    assert copies == [
        "--from=build /opt/renderfarm /opt/renderfarm",
        "--from=worker /src/build/worker/renderfarm-worker /usr/local/bin/renderfarm-worker",
    ], copies
    # The final stage's /usr/local/bin, on the image's PATH: the worker binary the server's
    # scene check finds there.
    usr_local_bin = base / "final" / "usr" / "local" / "bin"
    usr_local_bin.mkdir(parents=True)
    shutil.copy2(roots["worker"] / "src" / "build" / "worker" / "renderfarm-worker", usr_local_bin)
    entrypoint = json.loads(next(rest for op, rest in final if op == "ENTRYPOINT"))
    venv = roots["build"] / "opt" / "renderfarm"
    healthcheck = next(rest for op, rest in final if op == "HEALTHCHECK")
    return {
        "venv": venv,
        "usr_local_bin": usr_local_bin,
        "dist": roots["web"] / "src" / "web" / "dist",
        "command": [str(venv / "bin" / entrypoint[0]), *entrypoint[1:]],
        "healthcheck": json.loads(healthcheck[healthcheck.index("CMD ") + 4 :]),
    }


def _clean_env(venv: Path, usr_local_bin: Path | None = None, **extra: str) -> dict[str, str]:
    """The image's environment: its PATH first, nothing of this checkout (no PYTHONPATH, no
    RENDERFARM_WORKER_BINARY)."""
    keep = {k: v for k, v in os.environ.items() if k in ("HOME", "LANG", "TMPDIR")}
    image_path = f"{venv / 'bin'}:{usr_local_bin}:" if usr_local_bin else f"{venv / 'bin'}:"
    path = image_path + "/usr/sbin:/usr/bin:/sbin:/bin"
    return {**keep, "PATH": path, **extra}


@pytest.fixture(scope="module")
def image_server(image, tmp_path_factory):
    """The image's entrypoint from the reproduced environment, on loopback, with a token."""
    data = tmp_path_factory.mktemp("image-data")
    http_port, grpc_port = free_port(), free_port()
    env = _clean_env(
        image["venv"],
        image["usr_local_bin"],
        RENDERFARM_DATA_DIR=str(data),
        RENDERFARM_HTTP_HOST="127.0.0.1",
        RENDERFARM_HTTP_PORT=str(http_port),
        RENDERFARM_GRPC_HOST="127.0.0.1",
        RENDERFARM_GRPC_PORT=str(grpc_port),
        RENDERFARM_ADMIN_TOKEN=ADMIN_TOKEN,
    )
    log = open(data / "server.log", "wb")  # noqa: SIM115 (closed below)
    proc = subprocess.Popen(image["command"], env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{http_port}"

    def ready():
        assert proc.poll() is None, (data / "server.log").read_text()
        try:
            return httpx.get(f"{url}/readyz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    try:
        wait_until(ready, 120, "the image's server to be ready")
        yield {"url": url, "env": env}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def test_installed_package_carries_the_dashboard(image):
    """The package in the image's environment is a real (not editable) install, holding the
    dashboard the web stage built, and it is the one the entrypoint imports."""
    code = (
        "import json, renderfarm, renderfarm.api.static as r, importlib.metadata as m;"
        "print(json.dumps([renderfarm.__file__, str(r.WEB_DIST), m.requires('renderfarm')]))"
    )
    out = _run([str(image["venv"] / "bin" / "python"), "-c", code], cwd=image["venv"],
               env=_clean_env(image["venv"]))  # fmt: skip
    package_file, web_dist, requires = json.loads(out)
    package = Path(package_file).parent
    assert package.is_relative_to(image["venv"]), f"renderfarm imported from {package}"
    assert Path(web_dist) == package / "web"
    built = sorted(p.relative_to(image["dist"]) for p in image["dist"].rglob("*") if p.is_file())
    assert Path("index.html") in built and any(p.suffix == ".js" for p in built)
    for rel in built:
        assert (package / "web" / rel).read_bytes() == (image["dist"] / rel).read_bytes(), rel
    # pip installs the Swagger UI / ReDoc files into the image as a dependency of the package.
    assert any(r.startswith("fastapi-offline") for r in requires), requires


def test_image_health_check_passes(image, image_server):
    """The image's HEALTHCHECK command, with the image's PATH and the server's settings."""
    check = subprocess.run(
        image["healthcheck"], env=image_server["env"], capture_output=True, text=True, timeout=30
    )
    assert check.returncode == 0, check.stderr


def test_image_serves_the_dashboard_with_sign_in(image, image_server):
    url = image_server["url"]
    index = httpx.get(f"{url}/", timeout=10)
    assert index.status_code == 200
    assert index.content == (image["dist"] / "index.html").read_bytes(), "not web/dist's index"
    refs = re.findall(r'(?:src|href)="(/assets/[^"]+)"', index.text)
    assert any(r.endswith(".js") for r in refs) and any(r.endswith(".css") for r in refs), refs
    bundle = b""
    for ref in refs:
        asset = httpx.get(f"{url}{ref}", timeout=10)
        assert asset.status_code == 200, ref
        assert asset.content == (image["dist"] / ref.removeprefix("/")).read_bytes(), ref
        bundle += asset.content if ref.endswith(".js") else b""
    # The dashboard's sign-in: its code is in the bundle, and the server asks for it (401 to a
    # request without a token) and accepts the admin token for a session cookie.
    assert b"/session" in bundle and b"sign-out" in bundle
    assert httpx.get(f"{url}/api/v1/whoami", timeout=10).status_code == 401
    session = httpx.post(f"{url}/api/v1/session", json={"token": ADMIN_TOKEN}, timeout=10)
    assert session.status_code == 200, session.text
    assert "renderfarm_token" in session.cookies
    who = httpx.get(f"{url}/api/v1/whoami", cookies=session.cookies, timeout=10)
    assert who.status_code == 200 and who.json()["admin"] is True


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_image_api_docs_use_only_assets_the_server_serves(image_server, page):
    url = image_server["url"]
    html = httpx.get(f"{url}{page}", timeout=10)
    assert html.status_code == 200 and "text/html" in html.headers["content-type"]
    # Nothing from another host: no absolute or protocol-relative URL anywhere in the page.
    assert not re.search(r"(?:https?:)?//[\w.-]+\.[a-z]{2,}", html.text), html.text
    refs = set(re.findall(r'(?:src|href|spec-url)="([^"]+)"', html.text))
    refs |= set(re.findall(r"url: '([^']+)'", html.text))
    scripts = [r for r in refs if r.endswith(".js")]
    assert scripts, f"{page} references no script: {refs}"
    assert "/openapi.json" in refs
    kinds = {".js": "javascript", ".css": "text/css", ".json": "application/json"}
    for ref in sorted(refs):
        assert ref.startswith("/"), f"{page}: {ref} is not a path on this server"
        asset = httpx.get(f"{url}{ref}", timeout=30)
        assert asset.status_code == 200, f"{page}: {ref} answered {asset.status_code}"
        assert len(asset.content) > 100, ref
        suffix = Path(ref).suffix
        if suffix in kinds:
            assert kinds[suffix] in asset.headers["content-type"], (ref, asset.headers)
    # The scripts are the real Swagger UI / ReDoc bundles, not an error page.
    bundle = httpx.get(f"{url}{scripts[0]}", timeout=30).text
    assert ("SwaggerUIBundle" if page == "/docs" else "Redoc") in bundle


def test_image_checks_uploads_with_the_workers_loader(image_server):
    """The image's server finds renderfarm-worker on its PATH and runs its loader on an upload:
    the Cornell box is accepted, a node with two parents refused naming it."""
    from renderfarm.domain.scenes.pack import pack_gltf

    from .test_scene_acceptance import hostile

    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    url = f"{image_server['url']}/api/v1/jobs"
    settings = {"settings": '{"width": 16, "height": 16, "max_spp": 4}'}
    good = pack_gltf(ROOT / "examples" / "cornell-box.gltf")
    for data, status in ((good, 201), (hostile("shared-children"), 400)):
        r = httpx.post(url, headers=headers, data=settings, timeout=60,
                       files={"scene": ("scene.glb", data, "model/gltf-binary")})  # fmt: skip
        assert r.status_code == status, r.text
    assert r.json()["field"] == "scene.nodes[5].children[1]", r.text
