"""Static checks of deploy/: the compose file through docker-compose's own `config` check, the
Kubernetes manifests built with kustomize and validated offline against the Kubernetes API
types (kubernetes-validate's schemas, shipped in its wheel), the custom resources (KEDA,
CloudNativePG) by a check of their own, the Dockerfiles against the set-up script they install
through, the worker entrypoint, and the dashboards and autoscaling queries against the metrics
the server really exports. Nothing here needs a network, a Docker daemon or a cluster: the tools
come from scripts/install-deps.sh --deploy-tools."""

from __future__ import annotations

import os
import re
import shutil
import ssl
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import yaml

from .conftest import ROOT
from .tools import require_tool
from .waiting import wait_until

DEPLOY = ROOT / "deploy"
INSTALL = ROOT / "scripts" / "install-deps.sh"
COMPOSE = DEPLOY / "compose.yaml"
K8S = DEPLOY / "k8s"
DOCKER = DEPLOY / "docker"
ENTRYPOINT = DOCKER / "worker-entrypoint.sh"
MAKE_CERTS = DOCKER / "make-certs.sh"
DASHBOARD = DEPLOY / "grafana" / "dashboards" / "renderfarm.json"
# The Kubernetes versions the manifests must be valid for: the oldest with gRPC probes GA, and
# the newest whose schemas kubernetes-validate ships.
K8S_OLDEST = "1.27.0"
COMPOSE_ENV = {
    "RENDERFARM_DB_PASSWORD": "pw0123",
    "RENDERFARM_GRAFANA_PASSWORD": "pw4567",
    "RENDERFARM_ADMIN_TOKEN": "adm0123",
    "RENDERFARM_WORKER_TOKEN": "wrk4567",
}


def _run(args, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=120, **kwargs)


def _group(name: str) -> list[str]:
    out = _run(["bash", str(INSTALL), "--print", name])
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def _deployment_section(operations: str) -> str:
    start = operations.index("\n## Deployment\n")
    end = operations.find("\n## ", start + 1)
    return operations[start : end if end > 0 else None]


# ------------------------------------------------------------------------ set-up script
def test_install_script_groups_resolve_in_debian():
    assert _run(["bash", "-n", str(INSTALL)]).returncode == 0
    groups = {g: _group(g) for g in ("build", "web", "runtime-server", "runtime-worker", "deploy")}
    assert "python3" in groups["runtime-server"] and "docker-compose" in groups["deploy"]
    require_tool(shutil.which("apt-cache") is not None, "apt-cache: package names not checked")
    everything = sorted({p for packages in groups.values() for p in packages})
    # From the local package lists: no network. A name apt does not know is an error.
    shown = _run(["apt-cache", "show", "--no-all-versions", *everything])
    known = set(re.findall(r"^Package: (\S+)$", shown.stdout, re.M))
    assert not set(everything) - known, f"not in Debian: {set(everything) - known}"
    assert _run(["bash", str(INSTALL), "--print", "nonsense"]).returncode == 2
    assert _run(["bash", str(INSTALL), "--runtime", "nonsense"]).returncode == 2


def test_worker_runtime_packages_provide_every_library_the_worker_links(worker_binary):
    """The worker image's final stage installs only `--runtime worker`: it must ship every
    shared library the binary needs (NEEDED entries, by their Debian package)."""
    require_tool(
        shutil.which("dpkg") is not None and shutil.which("objdump") is not None,
        "dpkg and objdump (binutils, in the build packages)",
    )
    needed = re.findall(r"NEEDED\s+(\S+)", _run(["objdump", "-p", worker_binary]).stdout)
    assert needed
    cache = _run(["ldconfig", "-p"]).stdout
    runtime = set(_group("runtime-worker"))
    essential = {"libc6", "libgcc-s1"}  # in every Debian image (Essential / priority required)
    for lib in needed:
        m = re.search(rf"^\s*{re.escape(lib)} \(libc6,x86-64\) => (\S+)$", cache, re.M)
        assert m, f"{lib} is not in the linker cache"
        # dpkg knows a file by the path its package ships (merged /usr: /lib or /usr/lib).
        real = os.path.realpath(m.group(1))
        candidates = {m.group(1), real, real.removeprefix("/usr"), "/usr" + real}
        owners = _run(["dpkg", "-S", *sorted(candidates)]).stdout
        owner = owners.split(":")[0] if owners else ""
        assert owner in runtime | essential, f"{lib} comes from {owner}, not in --runtime worker"


# --------------------------------------------------------------------------- Dockerfiles
def _stages(dockerfile: Path) -> list[list[tuple[str, str]]]:
    """Instructions of each stage, with continuation lines joined."""
    text = re.sub(r"\\\n", " ", dockerfile.read_text())
    stages: list[list[tuple[str, str]]] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        op, _, rest = line.partition(" ")
        op = op.upper()
        if op == "FROM":
            stages.append([])
        if stages:
            stages[-1].append((op, rest.strip()))
        else:
            assert op == "ARG", f"{dockerfile.name}: {op} before the first FROM"
    return stages


@pytest.mark.parametrize("name", ["server", "worker"])
def test_dockerfile_multi_stage_slim_non_root_labelled(name):
    dockerfile = DOCKER / f"{name}.Dockerfile"
    stages = _stages(dockerfile)
    assert len(stages) >= 2, "multi-stage: a build stage and a runtime stage"
    for stage in stages:
        assert stage[0][1].split()[0] == "debian:bookworm-slim"
    build = next(s for s in stages if re.search(r"\sAS\s+build$", s[0][1], re.I))
    final = stages[-1]
    assert build is not final
    ops = dict(final)
    user = [rest for op, rest in final if op == "USER"]
    assert user and user[-1].split(":")[0] not in ("0", "root"), "the image runs as non-root"
    labels = " ".join(rest for op, rest in final if op == "LABEL")
    for key in ("title", "description", "version", "licenses"):
        assert f"org.opencontainers.image.{key}=" in labels
    assert "ENTRYPOINT" in ops and "HEALTHCHECK" in ops
    # Small: the final stage installs only the runtime packages, through the same script.
    runs = " ".join(rest for op, rest in final if op == "RUN")
    assert f"install-deps.sh --runtime {name}" in runs and "rm -rf /var/lib/apt/lists" in runs
    # No source from the build context: only what earlier stages built.
    assert not any(op == "COPY" and "--from=" not in rest and "/src" in rest for op, rest in final)
    assert not re.search(r"apt-get install|build-essential|-dev\b", runs)
    # Every COPY source of the build context exists and passes the image's .dockerignore.
    ignore = (DOCKER / f"{name}.Dockerfile.dockerignore").read_text().split()
    allowed = [p[1:] for p in ignore if p.startswith("!")]
    for stage in stages:
        for op, rest in stage:
            if op == "COPY" and not rest.startswith("--from"):
                src = rest.split()[0]
                assert (ROOT / src).exists(), f"COPY {src}: not in the repository"
                assert any(src == a or src.startswith(a + "/") for a in allowed), src


def test_dockerfiles_install_through_the_project_scripts():
    """The image recipes are the ones `make demo`, `make test` and CI run: the set-up script
    (default for the server, --apt-only for the worker: the same apt packages), `make proto`,
    and the worker's CMake invocation of the Makefile."""
    server = " ".join(
        r for s in _stages(DOCKER / "server.Dockerfile") for op, r in s if op == "RUN"
    )
    assert "scripts/install-deps.sh --apt-only" in server
    assert re.search(r"scripts/install-deps\.sh\s+&&", server), "the default set-up (apt + .venv)"
    assert "make proto" in server and "install-deps.sh --server-venv /opt/renderfarm" in server
    # The dashboard: a stage with Node from the set-up script runs the Makefile's `web` commands,
    # and the build stage puts web/dist into the package (renderfarm/web: its package data).
    web = next(s for s in _stages(DOCKER / "server.Dockerfile") if s[0][1].endswith(" AS web"))
    web_runs = " ".join(r for op, r in web if op == "RUN")
    assert "scripts/install-deps.sh --web" in web_runs
    recipe = re.search(r"^web:.*\n((?:\t.*\n)+)", (ROOT / "Makefile").read_text(), re.M)
    assert recipe, "the Makefile's web recipe"
    npm = re.findall(r"npm (?:ci|run)[^;}&|]*", recipe.group(1))
    assert len(npm) == 2, npm
    for command in npm:
        assert command.strip() in web_runs, command
    assert "COPY --from=web /src/web/dist server/renderfarm/web" in " ".join(
        f"{op} {r}" for s in _stages(DOCKER / "server.Dockerfile") for op, r in s
    )
    pyproject = (ROOT / "server" / "pyproject.toml").read_text()
    assert re.search(r'^renderfarm = \[.*"web/\*\*/\*"', pyproject, re.M)
    worker = " ".join(
        r for s in _stages(DOCKER / "worker.Dockerfile") for op, r in s if op == "RUN"
    )
    assert "scripts/install-deps.sh --apt-only" in worker
    makefile = (ROOT / "Makefile").read_text()
    configure = re.search(r"cmake -S worker -B \$\(BUILD\) (.*?)(?:>|$)", makefile, re.M)
    assert configure, "the Makefile's worker recipe"
    assert f"cmake -S worker -B build/worker {configure.group(1).strip()}" in worker
    # Each mode the Dockerfiles use is one the script knows (it rejects unknown ones).
    text = INSTALL.read_text()
    for mode in ("--apt-only", "--web", "--runtime", "--server-venv"):
        assert re.search(rf"^\s*{mode}\)", text, re.M), mode


# ---------------------------------------------------------------------- worker entrypoint
def _fake_worker(tmp_path: Path) -> Path:
    fake = tmp_path / "fake-worker"
    fake.write_text('#!/bin/sh\necho "pid=$$"\nfor a in "$@"; do echo "arg=$a"; done\n')
    fake.chmod(0o755)
    return fake


def test_worker_entrypoint_maps_environment_to_flags_and_execs(tmp_path):
    fake = _fake_worker(tmp_path)
    env = {
        "PATH": os.environ["PATH"],
        "RENDERFARM_WORKER_BINARY": str(fake),
        "RENDERFARM_SERVER": "server:50051",
        "RENDERFARM_WORKER_THREADS": "6",
        "RENDERFARM_WORKER_TOKEN": "s3cret with spaces",
        "RENDERFARM_WORKER_ID": "w-7",
        "RENDERFARM_WORKER_RESULT_INTERVAL_MS": "20",
    }
    # `exec`: the worker replaces the shell, so it is PID 1 in a container and gets SIGTERM.
    out = _run(["sh", "-c", f'echo "pid=$$"; exec {ENTRYPOINT} --prefetch 2'], env=env).stdout
    lines = out.splitlines()
    assert lines[0] == lines[1], "the entrypoint must exec the worker"
    args = [line[4:] for line in lines if line.startswith("arg=")]
    assert args == [
        "connect", "--server", "server:50051", "--threads", "6", "--result-interval-ms", "20",
        "--token", "s3cret with spaces", "--id", "w-7", "--prefetch", "2",
    ]  # fmt: skip
    tls = {
        **env,
        "RENDERFARM_WORKER_TLS": "1",
        "RENDERFARM_WORKER_CA_FILE": "/tls dir/ca.crt",
        "RENDERFARM_WORKER_CERT_FILE": "/tls dir/tls.crt",
        "RENDERFARM_WORKER_KEY_FILE": "/tls dir/tls.key",
        "RENDERFARM_WORKER_TLS_SERVER_NAME": "server",
    }
    out = _run([str(ENTRYPOINT)], env=tls).stdout
    assert [line[4:] for line in out.splitlines() if line.startswith("arg=")][-9:] == [
        "--tls", "--ca-file", "/tls dir/ca.crt", "--cert", "/tls dir/tls.crt",
        "--key", "/tls dir/tls.key", "--tls-server-name", "server",
    ]  # fmt: skip
    off = _run([str(ENTRYPOINT)], env={**env, "RENDERFARM_WORKER_TLS": "0"}).stdout
    assert "arg=--tls" not in off
    bad = _run([str(ENTRYPOINT)], env={**env, "RENDERFARM_WORKER_TLS": "yes"})
    assert bad.returncode == 64 and "RENDERFARM_WORKER_TLS" in bad.stderr
    minimal = {
        "PATH": env["PATH"],
        "RENDERFARM_WORKER_BINARY": str(fake),
        "RENDERFARM_SERVER": "s:1",
    }
    out = _run([str(ENTRYPOINT)], env=minimal).stdout
    assert [line[4:] for line in out.splitlines() if line.startswith("arg=")] == [
        "connect", "--server", "s:1",
    ]  # fmt: skip
    # Not a flag: the binary's own command (standalone render) goes through unchanged.
    out = _run([str(ENTRYPOINT), "render", "a.glb", "-o", "b.exr"], env=minimal).stdout
    assert "arg=render" in out and "arg=--server" not in out
    missing = _run(
        [str(ENTRYPOINT)], env={"PATH": env["PATH"], "RENDERFARM_WORKER_BINARY": str(fake)}
    )
    assert missing.returncode == 64 and "RENDERFARM_SERVER" in missing.stderr


def test_worker_entrypoint_runs_the_real_worker(worker_binary, tmp_path):
    """With the real binary: a command goes through unchanged (a standalone render), and in
    connect mode SIGTERM reaches the worker (exec), which stops cleanly with 0."""
    env = {"PATH": os.environ["PATH"], "RENDERFARM_WORKER_BINARY": worker_binary}
    out = tmp_path / "tiny.exr"
    args = ["render", str(ROOT / "examples" / "cornell-box.gltf"), "-o", str(out)]
    args += ["--spp", "1", "--width", "8", "--height", "8", "--threads", "1"]
    done = _run([str(ENTRYPOINT), *args], env=env)
    assert done.returncode == 0, done.stderr
    assert out.stat().st_size > 0
    # Port 1 on loopback: nothing listens, the worker keeps reconnecting with backoff.
    log = tmp_path / "worker.log"
    with open(log, "wb") as out_file:
        proc = subprocess.Popen(
            [str(ENTRYPOINT)],
            env={**env, "RENDERFARM_SERVER": "127.0.0.1:1", "RENDERFARM_WORKER_ID": "entrypoint"},
            stdout=out_file,
            stderr=subprocess.STDOUT,
        )
    try:
        # It logs "connecting to" once its SIGTERM handler is in place.
        wait_until(lambda: proc.poll() is not None or "connecting to" in log.read_text(), 30,
              "the worker to start connecting")  # fmt: skip
        assert proc.poll() is None, log.read_text()
        with open(f"/proc/{proc.pid}/comm") as comm:
            assert comm.read().strip() == "renderfarm-work", "exec: the worker is the process"
        proc.terminate()
        assert proc.wait(timeout=15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------------------- compose
def _compose(*args: str, compose_file: Path = COMPOSE, env: dict | None = None):
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.fail("docker-compose is missing: run scripts/install-deps.sh --deploy-tools")
    base = {k: v for k, v in os.environ.items() if not k.startswith("RENDERFARM_")}
    return _run([exe, "-f", str(compose_file), *args], env={**base, **(env or {})}, cwd=ROOT)


@pytest.fixture(scope="module")
def compose_config() -> dict:
    out = _compose("config", env=COMPOSE_ENV)
    assert out.returncode == 0, out.stderr
    return yaml.safe_load(out.stdout)


def test_compose_file_passes_docker_compose_config(compose_config):
    services = compose_config["services"]
    assert set(services) == {
        "postgres", "certs", "server", "server-2", "worker", "prometheus", "grafana"
    }  # fmt: skip
    for name, svc in services.items():
        if name == "certs":  # one-shot: makes the certificates before the server starts, exits
            assert svc.get("restart") == "no" and "healthcheck" not in svc
            continue
        assert svc.get("restart") == "unless-stopped", name
        assert "healthcheck" in svc, f"{name} has no health check"
    assert "postgres-data" in compose_config["volumes"]
    assert any(v.startswith("postgres-data:") for v in services["postgres"]["volumes"])
    # `up --scale worker=N`: nothing in the worker that only one container can have.
    worker = services["worker"]
    assert "container_name" not in worker and "ports" not in worker
    # Two replicas of one farm: the workers serve both (one stream to each).
    assert worker["environment"]["RENDERFARM_SERVER"] == "server:50051,server-2:50051"
    assert worker["depends_on"]["server"]["condition"] == "service_healthy"
    assert worker["depends_on"]["server-2"]["condition"] == "service_healthy"
    server, second = services["server"], services["server-2"]
    assert server["environment"]["RENDERFARM_REPLICA_ID"] == "server"
    assert second["environment"]["RENDERFARM_REPLICA_ID"] == "server-2"
    # One farm: the same database (the compose PostgreSQL), each server under its own name.
    replicas = [s["environment"]["RENDERFARM_REPLICA_ID"] for s in (server, second)]
    assert len(set(replicas)) == 2
    urls = {s["environment"]["RENDERFARM_DATABASE_URL"] for s in (server, second)}
    assert len(urls) == 1 and "@postgres:5432/" in urls.pop()
    # The same server otherwise: image, database, tokens, TLS, health check, mounts.
    same = {k: v for k, v in second["environment"].items() if k != "RENDERFARM_REPLICA_ID"}
    assert same == {k: v for k, v in server["environment"].items() if k != "RENDERFARM_REPLICA_ID"}
    for key in ("image", "build", "volumes", "healthcheck", "depends_on", "stop_grace_period"):
        assert second[key] == server[key], key
    # server-2 publishes its gRPC port alone (for remote workers), on a host port of its own.
    assert {p.rsplit(":", 1)[-1].split("/")[0] for p in second["ports"]} == {"50051"}
    host_ports = [p.rsplit(":", 1)[0] for p in server["ports"] + second["ports"]]
    assert len(set(host_ports)) == len(host_ports) == 3, host_ports
    assert set(services["prometheus"]["depends_on"]) >= {"server", "server-2"}
    assert server["depends_on"]["postgres"]["condition"] == "service_healthy"
    env = server["environment"]
    assert (
        env["RENDERFARM_DATABASE_URL"] == "postgresql://renderfarm:pw0123@postgres:5432/renderfarm"
    )
    assert env["RENDERFARM_HTTP_HOST"] == env["RENDERFARM_GRPC_HOST"] == "0.0.0.0"
    # Beyond loopback the server requires both tokens; compose refuses to start without them.
    assert env["RENDERFARM_ADMIN_TOKEN"] == "adm0123"
    assert env["RENDERFARM_WORKER_TOKEN"] == worker["environment"]["RENDERFARM_WORKER_TOKEN"]
    assert server["build"]["dockerfile"] == "deploy/docker/server.Dockerfile"
    assert worker["build"]["dockerfile"] == "deploy/docker/worker.Dockerfile"
    assert Path(server["build"]["context"]).resolve() == ROOT
    published = {p.split(":")[-1].split("/")[0] for p in server["ports"]}
    assert published == {"8080", "50051"}
    mounts = " ".join(services["prometheus"]["volumes"] + services["grafana"]["volumes"])
    assert str(DEPLOY / "prometheus" / "prometheus.yml") in mounts
    assert str(DEPLOY / "grafana" / "provisioning") in mounts


def _image_commands(dockerfile: Path) -> dict[str, Path]:
    """Commands the image's final stage copies into /usr/local/bin: name -> repository file."""
    return {
        dest.removeprefix("/usr/local/bin/"): ROOT / src
        for op, rest in _stages(dockerfile)[-1]
        if op == "COPY" and not rest.startswith("--from")
        for src, dest in [rest.split()]
        if dest.startswith("/usr/local/bin/")
    }


def test_compose_worker_health_check_passes_while_either_server_accepts(compose_config, tmp_path):
    """The workers' health check (compose's, and the worker image's own) tries every server of
    RENDERFARM_SERVER: healthy while one accepts, so a server restarting leaves them healthy;
    unhealthy when none does. Run here with each server host replaced by a loopback port."""
    import json
    import socket

    worker = compose_config["services"]["worker"]
    check = worker["healthcheck"]["test"]
    assert check[0] == "CMD", check
    commands = _image_commands(DOCKER / "worker.Dockerfile")
    image = next(r for op, r in _stages(DOCKER / "worker.Dockerfile")[-1] if op == "HEALTHCHECK")
    assert json.loads(image[image.index("CMD ") + 4 :]) == check[1:], "the image's own check"
    script = commands[check[1]]
    assert script.is_file() and os.access(script, os.X_OK), script
    bindir = tmp_path / "bin"
    bindir.mkdir()
    (bindir / check[1]).symlink_to(script)
    entries = worker["environment"]["RENDERFARM_SERVER"].split(",")
    assert len(entries) == 2
    listening = [socket.create_server(("127.0.0.1", 0)) for _ in entries]
    closed = []
    for _ in entries:
        with socket.create_server(("127.0.0.1", 0)) as s:
            closed.append(s.getsockname()[1])
    try:

        def health(ports: list[int]) -> int:
            env = {"PATH": f"{bindir}:{os.environ['PATH']}",
                   "RENDERFARM_SERVER": ",".join(f"127.0.0.1:{p}" for p in ports)}  # fmt: skip
            return _run(check[1:], env=env).returncode

        up = [s.getsockname()[1] for s in listening]
        assert health(up) == 0
        assert health([closed[0], up[1]]) == 0, "the first server away: still healthy"
        assert health([up[0], closed[1]]) == 0, "the second server away: still healthy"
        assert health(closed) != 0, "no server reachable: unhealthy"
        assert health(up[:1]) == 0 and health(closed[:1]) != 0, "one server, as with docker run"
    finally:
        for s in listening:
            s.close()


def test_compose_refuses_missing_passwords_and_invalid_files(tmp_path):
    out = _compose("config", env={"RENDERFARM_GRAFANA_PASSWORD": "x"})
    assert out.returncode != 0 and "RENDERFARM_DB_PASSWORD" in out.stderr
    no_token = {k: v for k, v in COMPOSE_ENV.items() if k != "RENDERFARM_ADMIN_TOKEN"}
    out = _compose("config", env=no_token)
    assert out.returncode != 0 and "RENDERFARM_ADMIN_TOKEN" in out.stderr
    # The check is a real schema validation: a misspelt key is an error.
    broken = tmp_path / "compose.yaml"
    broken.write_text(COMPOSE.read_text().replace("restart: unless-stopped", "restrat: always", 1))
    out = _compose("config", compose_file=broken, env=COMPOSE_ENV)
    assert out.returncode != 0 and "restrat" in out.stderr


def test_compose_settings_are_environment_variables_documented_in_the_docs(compose_config):
    text = COMPOSE.read_text()
    variables = set(re.findall(r"\$\{(\w+)", text))
    assert {"RENDERFARM_DB_PASSWORD", "RENDERFARM_WORKER_THREADS"} <= variables
    operations = (ROOT / "docs" / "operations.md").read_text()
    section = _deployment_section(operations)
    example = (DEPLOY / "env.example").read_text()
    for var in variables:
        assert f"`{var}`" in section, f"{var} is not documented in docs/operations.md, Deployment"
        assert var in example, f"{var} is not in deploy/env.example"
    # With everything at its default, the server gets exactly the server defaults.
    from renderfarm.infra.config import Settings

    env = compose_config["services"]["server"]["environment"]
    defaults = Settings()
    for key, value in env.items():
        field = key.removeprefix("RENDERFARM_").lower()
        if field in ("database_url", "http_host", "grpc_host", "worker_token", "admin_token"):
            continue
        if field == "replica_id":  # each server's own name (the test above)
            continue
        if field.startswith("tls_"):  # TLS: on in the deployment, checked on its own below
            continue
        assert float(value) == float(getattr(defaults, field)), key
    # A stopped server checkpoints, hands its jobs over and exits before Docker's SIGKILL.
    for name in ("server", "server-2"):
        svc = compose_config["services"][name]
        drain = svc["environment"].get("RENDERFARM_DRAIN_TIMEOUT_S", defaults.drain_timeout_s)
        drain = float(drain)
        grace = re.fullmatch(r"(\d+)s", svc["stop_grace_period"])
        assert grace and drain <= int(grace.group(1)), (name, svc["stop_grace_period"])


def _mounts(service: dict) -> dict[str, str]:
    """Container path -> source (volume name or host path) of a service's volumes."""
    return {v.split(":")[1]: v.split(":")[0] for v in service.get("volumes", [])}


def _in_mount(mounts: dict[str, str], path: str) -> tuple[str, str]:
    """(source, path inside it) of a container path under one of the mounts."""
    for target, source in mounts.items():
        if path.startswith(target.rstrip("/") + "/"):
            return source, path[len(target.rstrip("/")) + 1 :]
    pytest.fail(f"{path} is in none of the mounts {mounts}")


def _openssl_verify(ca: Path, cert: Path, purpose: str, hostname: str | None = None) -> None:
    args = ["openssl", "verify", "-CAfile", str(ca), "-purpose", purpose]
    if hostname:
        ip = re.fullmatch(r"[\d.]+|.*:.*", hostname)
        args += ["-verify_ip" if ip else "-verify_hostname", hostname]
    out = _run([*args, str(cert)])
    assert out.returncode == 0 and ": OK" in out.stdout, out.stdout + out.stderr


@pytest.fixture(scope="module")
def compose_certs(compose_config, tmp_path_factory) -> dict:
    """The `certs` service's command run here, each of its volumes a directory: the files the
    server, workers and Prometheus of the compose cluster read, by volume and file name."""
    if shutil.which("openssl") is None:
        pytest.fail("openssl is missing: run scripts/install-deps.sh --deploy-tools")
    certs = compose_config["services"]["certs"]
    assert certs["entrypoint"] == ["renderfarm-make-certs"]
    dockerfile = (DOCKER / "server.Dockerfile").read_text()
    assert "COPY deploy/docker/make-certs.sh /usr/local/bin/renderfarm-make-certs" in dockerfile
    base = tmp_path_factory.mktemp("compose-certs")
    mounts = _mounts(certs)
    dirs = {source: base / source.strip("/").replace("/", "_") for source in mounts.values()}
    args = [str(dirs[mounts[a]]) if a in mounts else a for a in certs["command"]]
    if os.geteuid() != 0 and args[:1] == ["--owner"]:
        args = args[2:]  # chown needs root; the files are the same
    made = _run([str(MAKE_CERTS), *args])
    assert made.returncode == 0, made.stderr
    return {"dirs": dirs, "args": args, "first": made.stdout}


def test_compose_runs_worker_traffic_over_tls_by_default(compose_config, compose_certs):
    services = compose_config["services"]
    certs, server, worker = services["certs"], services["server"], services["worker"]
    senv, wenv = server["environment"], worker["environment"]
    # The certificates exist before the server starts, from the server's own image.
    assert server["depends_on"]["certs"]["condition"] == "service_completed_successfully"
    assert certs["image"] == server["image"] and certs["build"] == server["build"]
    # The server serves REST and gRPC over TLS; mutual TLS is off until a client CA is set.
    assert senv["RENDERFARM_TLS_CLIENT_CA_FILE"] == ""
    assert "https://127.0.0.1:8080/readyz" in " ".join(server["healthcheck"]["test"])
    smounts, wmounts = _mounts(server), _mounts(worker)
    assert all(v.endswith(":ro") for v in server["volumes"] + worker["volumes"])
    files = {
        "server cert": _in_mount(smounts, senv["RENDERFARM_TLS_CERT_FILE"]),
        "server key": _in_mount(smounts, senv["RENDERFARM_TLS_KEY_FILE"]),
        "worker CA": _in_mount(wmounts, wenv["RENDERFARM_WORKER_CA_FILE"]),
        "worker cert": _in_mount(wmounts, wenv["RENDERFARM_WORKER_CERT_FILE"]),
        "worker key": _in_mount(wmounts, wenv["RENDERFARM_WORKER_KEY_FILE"]),
        # What an operator sets RENDERFARM_TLS_CLIENT_CA_FILE to for mutual TLS
        # (docs/operations.md).
        "client CA": _in_mount(smounts, "/etc/renderfarm/tls/ca.crt"),
    }
    dirs = compose_certs["dirs"]
    path = {k: dirs[source] / name for k, (source, name) in files.items()}
    for what, file in path.items():
        assert file.is_file(), f"the certs service made no {what} ({file})"
    assert oct(path["server key"].stat().st_mode & 0o777) == "0o600"
    assert oct(path["worker key"].stat().st_mode & 0o777) == "0o600"
    # The workers connect with TLS to each host of RENDERFARM_SERVER (both servers share the
    # certificate), which the certificate names; it is signed by the CA they check it against.
    assert wenv["RENDERFARM_WORKER_TLS"] == "1"
    hosts = [entry.rsplit(":", 1)[0] for entry in wenv["RENDERFARM_SERVER"].split(",")]
    assert hosts == ["server", "server-2"]
    for host in hosts:
        _openssl_verify(path["worker CA"], path["server cert"], "sslserver", host)
    _openssl_verify(path["worker CA"], path["server cert"], "sslserver", "127.0.0.1")
    _openssl_verify(path["client CA"], path["worker cert"], "sslclient")
    # Prometheus scrapes https://server:8080 checking the certificate against a mounted CA.
    prom = yaml.safe_load((DEPLOY / "prometheus" / "prometheus.yml").read_text())
    job = next(j for j in prom["scrape_configs"] if j["job_name"] == "renderfarm-server")
    assert job["scheme"] == "https"
    ca_source, ca_name = _in_mount(_mounts(services["prometheus"]), job["tls_config"]["ca_file"])
    for target in job["static_configs"][0]["targets"]:
        host = target.rsplit(":", 1)[0]
        _openssl_verify(dirs[ca_source] / ca_name, path["server cert"], "sslserver", host)
    # Once made, never again: a second run keeps the files (and an operator's own).
    before = {k: p.read_bytes() for k, p in path.items()}
    again = _run([str(MAKE_CERTS), *compose_certs["args"]])
    assert again.returncode == 0 and "nothing to do" in again.stdout
    assert {k: p.read_bytes() for k, p in path.items()} == before


def test_make_certs_refuses_an_incomplete_set(tmp_path):
    server, worker = tmp_path / "server", tmp_path / "worker"
    assert _run([str(MAKE_CERTS), str(server), str(worker), "a.example,10.0.0.9"]).returncode == 0
    text = _run(["openssl", "x509", "-noout", "-ext", "subjectAltName", "-in",
                 str(server / "tls.crt")]).stdout  # fmt: skip
    assert "DNS:a.example" in text and "IP Address:10.0.0.9" in text
    (worker / "ca.crt").unlink()
    out = _run([str(MAKE_CERTS), str(server), str(worker), "a.example"])
    assert out.returncode == 1 and str(worker / "ca.crt") in out.stderr
    out = _run([str(MAKE_CERTS), str(tmp_path / "s2"), str(tmp_path / "w2")])
    assert out.returncode == 1 and "usage" in out.stderr


def test_compose_certificates_carry_real_worker_traffic(compose_config, compose_certs, tmp_path):
    """The server of this checkout with the compose server's TLS files, and the real worker
    through the entrypoint with the compose worker's TLS environment (the certificate checked
    for the name `server`, as in compose): the worker joins over TLS; plaintext is refused."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    from renderfarm.cli.localfarm import free_port
    from renderfarm.infra.worker_binary import find_worker_binary

    services = compose_config["services"]
    dirs = compose_certs["dirs"]

    def host_path(service: dict, path: str) -> str:
        source, name = _in_mount(_mounts(service), path)
        return str(dirs[source] / name)

    senv, wenv = services["server"]["environment"], services["worker"]["environment"]
    http_port, grpc_port = free_port(), free_port()
    server_env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("RENDERFARM_")},
        "RENDERFARM_TLS_CERT_FILE": host_path(services["server"], senv["RENDERFARM_TLS_CERT_FILE"]),
        "RENDERFARM_TLS_KEY_FILE": host_path(services["server"], senv["RENDERFARM_TLS_KEY_FILE"]),
        "RENDERFARM_DATA_DIR": str(tmp_path / "server"),
        "RENDERFARM_HTTP_PORT": str(http_port),
        "RENDERFARM_GRPC_PORT": str(grpc_port),
    }
    worker_env = {
        "PATH": os.environ["PATH"],
        "RENDERFARM_WORKER_BINARY": find_worker_binary(),
        "RENDERFARM_SERVER": f"127.0.0.1:{grpc_port}",
        "RENDERFARM_WORKER_ID": "compose-tls",
        "RENDERFARM_WORKER_THREADS": "1",
        "RENDERFARM_WORKER_TLS": wenv["RENDERFARM_WORKER_TLS"],
        "RENDERFARM_WORKER_TLS_SERVER_NAME": wenv["RENDERFARM_SERVER"].rsplit(":", 1)[0],
        **{
            k: host_path(services["worker"], wenv[k])
            for k in ("RENDERFARM_WORKER_CA_FILE", "RENDERFARM_WORKER_CERT_FILE",
                      "RENDERFARM_WORKER_KEY_FILE")
        },
    }  # fmt: skip
    ca = ssl.create_default_context(cafile=worker_env["RENDERFARM_WORKER_CA_FILE"])
    logs = {name: open(tmp_path / f"{name}.log", "wb") for name in ("server", "worker")}  # noqa: SIM115
    procs = [
        subprocess.Popen([sys.executable, "-m", "renderfarm", "server"], env=server_env,
                         stdout=logs["server"], stderr=subprocess.STDOUT),
    ]  # fmt: skip
    try:
        url = f"https://127.0.0.1:{http_port}"

        def ready() -> bool:
            assert procs[0].poll() is None, (tmp_path / "server.log").read_text()
            try:
                return httpx.get(f"{url}/readyz", verify=ca, timeout=2).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(ready, 120, "the TLS server to be ready")
        # The compose server's health check (here on this server's port) passes over https, and
        # the server survives it: the checking process exits as soon as it has read the answer,
        # so the server's last TLS write meets a closed socket (with SIGPIPE not ignored, that
        # killed the server).
        check = services["server"]["healthcheck"]["test"]
        assert check[:2] == ["CMD", "python3"]
        check = [c.replace("127.0.0.1:8080", f"127.0.0.1:{http_port}") for c in check[2:]]
        for _ in range(20):
            done = _run([sys.executable, *check])
            assert done.returncode == 0, done.stderr
        assert httpx.get(f"{url}/readyz", verify=ca, timeout=5).status_code == 200
        assert procs[0].poll() is None, (tmp_path / "server.log").read_text()
        procs.append(
            subprocess.Popen([str(ENTRYPOINT)], env=worker_env, stdout=logs["worker"],
                             stderr=subprocess.STDOUT)
        )  # fmt: skip

        def joined() -> bool:
            assert procs[0].poll() is None, (tmp_path / "server.log").read_text()
            assert procs[1].poll() is None, (tmp_path / "worker.log").read_text()
            workers = httpx.get(f"{url}/api/v1/workers", verify=ca, timeout=5).json()
            return any(w["id"] == "compose-tls" for w in workers)

        wait_until(joined, 60, "the worker to join over TLS")
        assert httpx.get(f"{url}/readyz", verify=ca, timeout=5).status_code == 200
        assert procs[0].poll() is None, (tmp_path / "server.log").read_text()
        # The gRPC port speaks TLS only: a plaintext health check gets no answer.
        with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as channel:
            with pytest.raises(grpc.RpcError) as refused:
                health_pb2_grpc.HealthStub(channel).Check(
                    health_pb2.HealthCheckRequest(), timeout=5
                )
            assert refused.value.code() in (
                grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED
            )  # fmt: skip
    finally:
        for proc in reversed(procs):
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for log in logs.values():
            log.close()


# ---------------------------------------------------------------- Prometheus and Grafana
def _dashboard_queries() -> list[str]:
    import json

    dash = json.loads(DASHBOARD.read_text())
    return [t["expr"] for p in dash["panels"] for t in p["targets"]]


def _scaledobject_queries() -> list[str]:
    so = yaml.safe_load((K8S / "base" / "worker-scaledobject.yaml").read_text())
    return [t["metadata"]["query"] for t in so["spec"]["triggers"]]


def test_prometheus_scrapes_the_server_and_grafana_is_provisioned(compose_config):
    import json

    prom = yaml.safe_load((DEPLOY / "prometheus" / "prometheus.yml").read_text())
    jobs = {j["job_name"]: j for j in prom["scrape_configs"]}
    server = jobs["renderfarm-server"]
    assert server["metrics_path"] == "/metrics"
    # Every server of the farm: each exports the figures of the jobs it owns.
    assert server["static_configs"][0]["targets"] == [
        f"{name}:8080" for name in compose_config["services"] if name.startswith("server")
    ]
    datasources = yaml.safe_load(
        (DEPLOY / "grafana/provisioning/datasources/prometheus.yaml").read_text()
    )["datasources"]
    assert datasources[0]["url"] == "http://prometheus:9090"
    providers = yaml.safe_load(
        (DEPLOY / "grafana/provisioning/dashboards/renderfarm.yaml").read_text()
    )["providers"]
    dashboards_dir = providers[0]["options"]["path"]
    grafana_mounts = compose_config["services"]["grafana"]["volumes"]
    assert any(m.split(":")[1] == dashboards_dir for m in grafana_mounts)
    dash = json.loads(DASHBOARD.read_text())
    titles = " | ".join(p["title"].lower() for p in dash["panels"])
    for needed in ("throughput", "queue depth", "jobs by state", "per worker"):
        assert needed in titles, needed
    for panel in dash["panels"]:
        assert panel["datasource"]["uid"] == datasources[0]["uid"]
    # Several servers: each exports its own jobs' figures (summed), but a worker serving every
    # server is connected to each, so a sum of the connected workers counts it once per server.
    for query in _dashboard_queries():
        assert not re.search(r"sum\b[^;]*renderfarm_workers_connected", query), query


def test_dashboard_and_autoscaling_use_metrics_the_server_exports(farm):
    """Every metric name in the dashboard's and KEDA's queries is on the real server's
    /metrics (families are listed even before they have samples)."""
    text = httpx.get(f"{farm.url}/metrics", timeout=10).text
    exported = set(re.findall(r"^# TYPE (\w+) (\w+)", text, re.M))
    names = {n for n, _ in exported} | {f"{n}_total" for n, t in exported if t == "counter"}
    for query in _dashboard_queries() + _scaledobject_queries():
        for metric in re.findall(r"\brenderfarm_\w+", query):
            assert metric in names, f"{metric} (in {query!r}) is not exported by the server"


# ---------------------------------------------------------------------------- Kubernetes
def _kustomize() -> list[str]:
    if shutil.which("kustomize"):
        return ["kustomize", "build"]
    local = ROOT / ".venv" / "bin" / "kustomize"
    if local.exists():
        return [str(local), "build"]
    if shutil.which("kubectl"):
        return ["kubectl", "kustomize"]
    pytest.fail("no kustomize: run scripts/install-deps.sh --deploy-tools")


SECRETS = {
    "external-db": "RENDERFARM_DATABASE_URL=postgresql://rf:pw@db.internal:5432/renderfarm\n"
    "RENDERFARM_WORKER_TOKEN=tok\nRENDERFARM_ADMIN_TOKEN=adm\n",
    "cloudnative-pg": "RENDERFARM_WORKER_TOKEN=tok\nRENDERFARM_ADMIN_TOKEN=adm\n",
}


@pytest.fixture(scope="module")
def k8s_tree(tmp_path_factory) -> Path:
    """A copy of deploy/k8s with the (git-ignored) secrets.env an operator writes."""
    tree = tmp_path_factory.mktemp("k8s") / "k8s"
    shutil.copytree(K8S, tree, ignore=shutil.ignore_patterns("secrets.env"))
    for overlay, secrets in SECRETS.items():
        (tree / "overlays" / overlay / "secrets.env").write_text(secrets)
    return tree


def _build(tree: Path, overlay: str) -> list[dict]:
    out = _run([*_kustomize(), str(tree / "overlays" / overlay)])
    assert out.returncode == 0, out.stderr
    return [d for d in yaml.safe_load_all(out.stdout) if d]


def _check_custom_resource(doc: dict, docs: list[dict]) -> None:
    """The fields of KEDA's ScaledObject and CloudNativePG's Cluster these manifests use, with
    their types (their CRD schemas are not in kubernetes-validate)."""
    spec = doc["spec"]
    if doc["apiVersion"] == "keda.sh/v1alpha1" and doc["kind"] == "ScaledObject":
        allowed = {
            "scaleTargetRef", "minReplicaCount", "maxReplicaCount", "pollingInterval",
            "cooldownPeriod", "idleReplicaCount", "advanced", "triggers", "fallback",
        }  # fmt: skip
        assert set(spec) <= allowed, set(spec) - allowed
        target = spec["scaleTargetRef"]
        assert target["kind"] == "Deployment" and target["apiVersion"] == "apps/v1"
        assert any(
            d["kind"] == "Deployment" and d["metadata"]["name"] == target["name"] for d in docs
        )
        for key in ("minReplicaCount", "maxReplicaCount", "pollingInterval", "cooldownPeriod"):
            assert isinstance(spec[key], int) and spec[key] >= 0, key
        assert spec["minReplicaCount"] <= spec["maxReplicaCount"]
        behavior = spec["advanced"]["horizontalPodAutoscalerConfig"]["behavior"]
        assert set(behavior) <= {"scaleUp", "scaleDown"}
        for trigger in spec["triggers"]:
            assert trigger["type"] == "prometheus"
            meta = trigger["metadata"]
            assert all(isinstance(v, str) for v in meta.values()), "trigger metadata are strings"
            assert meta["serverAddress"].startswith("http") and meta["query"]
            float(meta["threshold"]), float(meta["activationThreshold"])
    elif doc["apiVersion"] == "postgresql.cnpg.io/v1" and doc["kind"] == "Cluster":
        allowed = {
            "instances", "imageName", "primaryUpdateStrategy", "bootstrap", "storage",
            "resources", "postgresql", "monitoring", "backup", "affinity",
        }  # fmt: skip
        assert set(spec) <= allowed, set(spec) - allowed
        assert isinstance(spec["instances"], int) and spec["instances"] >= 1
        assert spec["primaryUpdateStrategy"] in ("unsupervised", "supervised")
        assert set(spec["bootstrap"]) == {"initdb"}
        assert re.fullmatch(r"\d+(Mi|Gi|Ti)", spec["storage"]["size"])
    elif doc["apiVersion"] == "cert-manager.io/v1" and doc["kind"] == "Issuer":
        assert len(spec) == 1 and set(spec) <= {"selfSigned", "ca"}, spec
        if "ca" in spec:
            assert set(spec["ca"]) == {"secretName"}
            assert any(
                d["kind"] == "Certificate" and d["spec"]["secretName"] == spec["ca"]["secretName"]
                and d["spec"].get("isCA") for d in docs
            ), "the CA Issuer's secret is made by a CA Certificate"  # fmt: skip
    elif doc["apiVersion"] == "cert-manager.io/v1" and doc["kind"] == "Certificate":
        allowed = {
            "secretName", "isCA", "commonName", "dnsNames", "ipAddresses", "duration",
            "renewBefore", "usages", "privateKey", "issuerRef",
        }  # fmt: skip
        assert set(spec) <= allowed, set(spec) - allowed
        assert isinstance(spec["secretName"], str) and spec["secretName"]
        for key in ("duration", "renewBefore"):
            assert re.fullmatch(r"\d+h", spec[key]), key
        assert int(spec["renewBefore"][:-1]) < int(spec["duration"][:-1])
        key_usages = {"digital signature", "key encipherment", "cert sign"}
        assert set(spec.get("usages", [])) <= key_usages | {"server auth", "client auth"}
        assert set(spec["privateKey"]) <= {"algorithm", "size", "rotationPolicy", "encoding"}
        assert spec["privateKey"]["algorithm"] in ("RSA", "ECDSA", "Ed25519")
        assert spec["privateKey"].get("rotationPolicy", "Always") in ("Always", "Never")
        ref = spec["issuerRef"]
        assert ref["group"] == "cert-manager.io" and ref["kind"] == "Issuer"
        assert any(d["kind"] == "Issuer" and d["metadata"]["name"] == ref["name"] for d in docs)
        assert all(isinstance(n, str) for n in spec.get("dnsNames", []))
    else:
        pytest.fail(f"no check for {doc['apiVersion']} {doc['kind']}")


def _env_refs(pod_spec: dict):
    for c in pod_spec["containers"]:
        for e in c.get("env", []):
            ref = e.get("valueFrom", {})
            if "secretKeyRef" in ref:
                yield "Secret", ref["secretKeyRef"]["name"], ref["secretKeyRef"]["key"]
            if "configMapKeyRef" in ref:
                yield "ConfigMap", ref["configMapKeyRef"]["name"], ref["configMapKeyRef"]["key"]
        for e in c.get("envFrom", []):
            if "configMapRef" in e:
                yield "ConfigMap", e["configMapRef"]["name"], None
            if "secretRef" in e:
                yield "Secret", e["secretRef"]["name"], None
    for v in pod_spec.get("volumes", []):
        if "secret" in v:
            yield "Secret", v["secret"]["secretName"], None


@pytest.mark.parametrize("overlay", ["external-db", "cloudnative-pg"])
def test_kubernetes_manifests_build_and_validate_offline(k8s_tree, overlay):
    import base64

    import kubernetes_validate as kv

    docs = _build(k8s_tree, overlay)
    kinds = sorted(f"{d['kind']}/{d['metadata']['name']}" for d in docs)
    expected = {
        "Namespace/renderfarm", "Deployment/renderfarm-server", "Service/renderfarm-server",
        "Deployment/renderfarm-worker", "PodDisruptionBudget/renderfarm-worker",
        "ScaledObject/renderfarm-worker", "Service/renderfarm-server-workers",
        "PodDisruptionBudget/renderfarm-server",
    }  # fmt: skip
    assert expected <= set(kinds), kinds
    assert any(k.startswith("ConfigMap/renderfarm-config-") for k in kinds)
    assert any(k.startswith("Secret/renderfarm-secrets-") for k in kinds)
    if overlay == "cloudnative-pg":
        assert "Cluster/renderfarm-db" in kinds
    for doc in docs:
        if doc["kind"] != "Namespace":
            assert doc["metadata"]["namespace"] == "renderfarm", doc["metadata"]["name"]
        try:
            for version in (K8S_OLDEST, kv.latest_version()):
                kv.validate(doc, version, strict=True)
        except kv.SchemaNotFoundError:
            _check_custom_resource(doc, docs)

    by = {(d["kind"], d["metadata"]["name"]): d for d in docs}
    objects = {(d["kind"], d["metadata"]["name"]) for d in docs}
    generated = {("Secret", "renderfarm-db-app")} if overlay == "cloudnative-pg" else set()
    # cert-manager makes the Secrets its Certificates name.
    generated |= {("Secret", d["spec"]["secretName"]) for d in docs if d["kind"] == "Certificate"}
    server = by[("Deployment", "renderfarm-server")]["spec"]
    worker = by[("Deployment", "renderfarm-worker")]["spec"]
    # Every Secret and ConfigMap referenced exists in the build (or is the operator's).
    for deployment in (server, worker):
        for kind, name, key in _env_refs(deployment["template"]["spec"]):
            assert (kind, name) in objects | generated, f"{kind} {name} is not defined"
            if (kind, name) in by and key is not None:
                data = by[(kind, name)].get("data", {})
                assert key in data, f"{kind} {name} has no key {key}"
    secrets = next(
        d
        for d in docs
        if d["kind"] == "Secret" and d["metadata"]["name"].startswith("renderfarm-secrets")
    )
    decoded = {k: base64.b64decode(v).decode() for k, v in secrets["data"].items()}
    assert decoded["RENDERFARM_WORKER_TOKEN"] == "tok"
    server_env = {e["name"]: e for e in server["template"]["spec"]["containers"][0]["env"]}
    url_ref = server_env["RENDERFARM_DATABASE_URL"]["valueFrom"]["secretKeyRef"]
    if overlay == "cloudnative-pg":
        assert (url_ref["name"], url_ref["key"]) == ("renderfarm-db-app", "uri")
        assert by[("Cluster", "renderfarm-db")]["spec"]["bootstrap"]["initdb"]["database"]
    else:
        assert decoded["RENDERFARM_DATABASE_URL"].startswith("postgresql://")

    # The servers: three replicas of one farm, replaced one at a time (each hands its jobs
    # over on SIGTERM), at most one away for a voluntary disruption; each named by its pod.
    assert server["replicas"] == 3 and server["strategy"]["type"] == "RollingUpdate"
    assert server["strategy"]["rollingUpdate"] == {"maxUnavailable": 1, "maxSurge": 0}
    assert server_env["RENDERFARM_REPLICA_ID"]["valueFrom"]["fieldRef"]["fieldPath"] == (
        "metadata.name"
    )
    # On SIGTERM a server drains (checkpoint, release its jobs, exit) before the kubelet's
    # SIGKILL: the drain timeout (set, or the server's default) fits the grace period.
    from renderfarm.infra.config import Settings

    drain = server_env.get("RENDERFARM_DRAIN_TIMEOUT_S", {}).get("value")
    drain = float(drain) if drain is not None else Settings().drain_timeout_s
    assert drain <= server["template"]["spec"]["terminationGracePeriodSeconds"]
    spdb = by[("PodDisruptionBudget", "renderfarm-server")]["spec"]
    slabels = server["template"]["metadata"]["labels"]
    assert spdb["maxUnavailable"] == 1
    assert all(slabels.get(k) == v for k, v in spdb["selector"]["matchLabels"].items())
    assert server["selector"]["matchLabels"] == spdb["selector"]["matchLabels"]
    c = server["template"]["spec"]["containers"][0]
    ports = {p["name"]: p["containerPort"] for p in c["ports"]}
    # Probes over HTTPS (the server serves TLS only; the kubelet's gRPC probes cannot).
    assert c["livenessProbe"]["httpGet"]["path"] == "/healthz"
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert c["startupProbe"]["httpGet"]["path"] == "/healthz"
    for probe in ("livenessProbe", "readinessProbe", "startupProbe"):
        assert c[probe]["httpGet"]["scheme"] == "HTTPS" and c[probe]["httpGet"]["port"] == "http"
    annotations = server["template"]["metadata"]["annotations"]
    assert annotations["prometheus.io/scheme"] == "https"
    config = next(d for d in docs if d["kind"] == "ConfigMap")["data"]
    assert int(config["RENDERFARM_HTTP_PORT"]) == ports["http"]
    assert int(config["RENDERFARM_GRPC_PORT"]) == ports["grpc"]
    assert config["RENDERFARM_HTTP_HOST"] == config["RENDERFARM_GRPC_HOST"] == "0.0.0.0"
    service = by[("Service", "renderfarm-server")]["spec"]
    labels = server["template"]["metadata"]["labels"]
    assert all(labels.get(k) == v for k, v in service["selector"].items())
    assert {p["targetPort"] for p in service["ports"]} == {"http", "grpc"}
    assert service.get("clusterIP") != "None", "clients use one address, any replica answers"
    Settings(**{k.removeprefix("RENDERFARM_").lower(): v for k, v in config.items()})

    # The workers: resource requests, a preStop drain, the server's Service as their server.
    w = worker["template"]["spec"]
    wc = w["containers"][0]
    assert wc["resources"]["requests"]["cpu"] and wc["resources"]["requests"]["memory"]
    assert "kill -TERM 1" in " ".join(wc["lifecycle"]["preStop"]["exec"]["command"])
    assert w["terminationGracePeriodSeconds"] >= 60
    wenv = {e["name"]: e for e in wc["env"]}
    # The workers serve every server: a headless Service resolves to each ready server pod.
    assert wenv["RENDERFARM_SERVER"]["value"] == f"renderfarm-server-workers:{ports['grpc']}"
    headless = by[("Service", "renderfarm-server-workers")]["spec"]
    assert headless["clusterIP"] == "None" and headless["publishNotReadyAddresses"] is False
    assert headless["selector"] == service["selector"]
    assert all(slabels.get(k) == v for k, v in headless["selector"].items())
    worker_labels = worker["template"]["metadata"]["labels"]
    assert not all(worker_labels.get(k) == v for k, v in headless["selector"].items()), (
        "the headless Service selects the server pods only"
    )
    assert [(p["port"], p["targetPort"]) for p in headless["ports"]] == [(ports["grpc"], "grpc")]
    pdb = by[("PodDisruptionBudget", "renderfarm-worker")]["spec"]
    wlabels = worker["template"]["metadata"]["labels"]
    assert all(wlabels.get(k) == v for k, v in pdb["selector"]["matchLabels"].items())
    # Each server exports the queue depth of the jobs it owns: the farm's is their sum.
    assert re.match(r"sum\(renderfarm_queue_depth\b", _scaledobject_queries()[0])
    _check_kubernetes_tls(docs, config)


def _secret_file(pod_spec: dict, container: dict, path: str) -> tuple[str, str]:
    """(Secret name, key) of the file `path` in a container, from a secret volume mount."""
    volumes = {v["name"]: v for v in pod_spec["volumes"]}
    for mount in container["volumeMounts"]:
        prefix = mount["mountPath"].rstrip("/") + "/"
        if path.startswith(prefix) and "secret" in volumes[mount["name"]]:
            assert mount.get("readOnly") is True, mount
            return volumes[mount["name"]]["secret"]["secretName"], path[len(prefix) :]
    pytest.fail(f"{path} is not in a mounted Secret")


def _check_kubernetes_tls(docs: list[dict], config: dict) -> None:
    """TLS is on: the server serves with a cert-manager certificate for the name the workers
    connect to; the workers use TLS, check it against the CA that signed it, and carry a client
    certificate of the same CA. The Secrets cert-manager writes hold tls.crt, tls.key, ca.crt."""
    by = {(d["kind"], d["metadata"]["name"]): d for d in docs}
    certificates = {d["spec"]["secretName"]: d for d in docs if d["kind"] == "Certificate"}
    cert_manager_keys = {"tls.crt", "tls.key", "ca.crt"}
    server_pod = by[("Deployment", "renderfarm-server")]["spec"]["template"]["spec"]
    worker_pod = by[("Deployment", "renderfarm-worker")]["spec"]["template"]["spec"]
    sc, wc = server_pod["containers"][0], worker_pod["containers"][0]
    cert_secret, cert_key = _secret_file(server_pod, sc, config["RENDERFARM_TLS_CERT_FILE"])
    key_secret, key_key = _secret_file(server_pod, sc, config["RENDERFARM_TLS_KEY_FILE"])
    assert cert_secret == key_secret and (cert_key, key_key) == ("tls.crt", "tls.key")
    server_cert = certificates[cert_secret]["spec"]
    assert "server auth" in server_cert["usages"]
    wenv = {e["name"]: e.get("value") for e in wc["env"]}
    assert wenv["RENDERFARM_WORKER_TLS"] == "1"
    host = wenv["RENDERFARM_SERVER"].rsplit(":", 1)[0]
    assert host in server_cert["dnsNames"], "the workers' server name is not in the certificate"
    # Every form of both Services' names (the workers' headless one, the clients' one): a
    # worker or client in another namespace, or with the cluster domain, checks it too.
    namespace = by[("Deployment", "renderfarm-server")]["metadata"]["namespace"]
    for name in (host, "renderfarm-server"):
        forms = [name, f"{name}.{namespace}", f"{name}.{namespace}.svc"]
        forms.append(f"{name}.{namespace}.svc.cluster.local")
        missing = set(forms) - set(server_cert["dnsNames"])
        assert not missing, f"not in the server certificate: {missing}"
    assert any(
        d["kind"] == "Service" and d["metadata"]["name"] == host for d in docs
    ), "the workers connect to the server's Service"  # fmt: skip
    ca_secret, ca_key = _secret_file(worker_pod, wc, wenv["RENDERFARM_WORKER_CA_FILE"])
    wcert_secret, wcert_key = _secret_file(worker_pod, wc, wenv["RENDERFARM_WORKER_CERT_FILE"])
    wkey_secret, wkey_key = _secret_file(worker_pod, wc, wenv["RENDERFARM_WORKER_KEY_FILE"])
    assert ca_secret == wcert_secret == wkey_secret
    assert {ca_key, wcert_key, wkey_key} == cert_manager_keys
    worker_cert = certificates[ca_secret]["spec"]
    assert "client auth" in worker_cert["usages"]
    # One CA signs both: the worker's ca.crt is the CA of the server's certificate.
    assert worker_cert["issuerRef"] == server_cert["issuerRef"]
    issuer = by[("Issuer", server_cert["issuerRef"]["name"])]["spec"]
    assert certificates[issuer["ca"]["secretName"]]["spec"]["isCA"] is True
    # The key files are readable by the containers' group only (fsGroup 10001).
    for pod in (server_pod, worker_pod):
        assert pod["securityContext"]["fsGroup"] == pod["securityContext"]["runAsGroup"]
        for v in pod["volumes"]:
            if "secret" in v and v["secret"]["secretName"] in certificates:
                assert v["secret"]["defaultMode"] == 0o440
    # Mutual TLS is the component's: off by default.
    assert "RENDERFARM_TLS_CLIENT_CA_FILE" not in {e["name"] for e in sc.get("env", [])}
    assert "RENDERFARM_TLS_CLIENT_CA_FILE" not in config


def test_kubernetes_mutual_tls_component(k8s_tree):
    """With components/mutual-tls the server requires client certificates signed by the CA of
    its own Secret, the one that signed the workers' certificates."""
    import kubernetes_validate as kv

    overlay = k8s_tree / "overlays" / "mutual-tls-check"
    overlay.mkdir()
    (overlay / "kustomization.yaml").write_text(
        "apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\n"
        "resources:\n  - ../external-db\ncomponents:\n  - ../../components/mutual-tls\n"
    )
    docs = _build(k8s_tree, "mutual-tls-check")
    server = next(d for d in docs if d["metadata"]["name"] == "renderfarm-server"
                  and d["kind"] == "Deployment")  # fmt: skip
    kv.validate(server, K8S_OLDEST, strict=True)
    pod = server["spec"]["template"]["spec"]
    env = {e["name"]: e for e in pod["containers"][0]["env"]}
    client_ca = env["RENDERFARM_TLS_CLIENT_CA_FILE"]["value"]
    secret, key = _secret_file(pod, pod["containers"][0], client_ca)
    assert key == "ca.crt" and secret == "renderfarm-server-tls"
    # The rest of the server's environment is still there (a merge, not a replacement).
    assert {"RENDERFARM_DATABASE_URL", "RENDERFARM_WORKER_TOKEN"} <= set(env)


def test_kubernetes_validation_rejects_invalid_manifests(k8s_tree, tmp_path):
    """The offline validation is real: a misspelt field and a wrong type are rejected."""
    import kubernetes_validate as kv

    docs = _build(k8s_tree, "external-db")
    deployment = next(d for d in docs if d["kind"] == "Deployment")
    deployment["spec"]["replica"] = 2
    with pytest.raises(kv.ValidationError):
        kv.validate(deployment, K8S_OLDEST, strict=True)
    del deployment["spec"]["replica"]
    deployment["spec"]["template"]["spec"]["containers"][0]["ports"][0]["containerPort"] = "http"
    with pytest.raises(kv.ValidationError):
        kv.validate(deployment, K8S_OLDEST, strict=True)


def test_kubernetes_overlay_without_secrets_does_not_build(tmp_path):
    """No default credentials: an overlay without its secrets.env refuses to build."""
    tree = tmp_path / "k8s"
    shutil.copytree(K8S, tree, ignore=shutil.ignore_patterns("secrets.env"))
    out = _run([*_kustomize(), str(tree / "overlays" / "external-db")])
    assert out.returncode != 0 and "secrets.env" in out.stderr


def test_docs_document_each_deployment_step():
    operations = (ROOT / "docs" / "operations.md").read_text()
    section = _deployment_section(operations)
    for command in (
        "docker compose -f deploy/compose.yaml up",
        "--scale worker=",
        "kubectl apply -k deploy/k8s/overlays/external-db",
        "kubectl apply -k deploy/k8s/overlays/cloudnative-pg",
        "deploy/netns/farm.sh up",
        "make test-deploy",
    ):
        assert command in section, command
    # TLS: how it is on by default, how to bring your own certificates, how to turn on mutual TLS.
    tls = section[section.index("\n### TLS of the deployments\n") :]
    for needed in (
        "RENDERFARM_TLS_CLIENT_CA_FILE=/etc/renderfarm/tls/ca.crt",
        "../../components/mutual-tls",
        "NETFARM_MUTUAL_TLS=1",
        "RENDERFARM_TLS_SERVER_DIR",
        "RENDERFARM_TLS_WORKER_DIR",
        "remove `../../components/cert-manager`",
        "RENDERFARM_WORKER_TLS_SERVER_NAME",
    ):
        assert needed in tls, needed
    # Commands shown in the examples of docs/operations.md name files that exist.
    for path in re.findall(r"deploy/[\w./-]+", section):
        path = path.rstrip(".")
        assert (ROOT / path).exists() or path.endswith(("secrets.env", "/.env")), path
