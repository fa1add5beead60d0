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
import subprocess
from pathlib import Path

import httpx
import pytest
import yaml

from .conftest import ROOT

DEPLOY = ROOT / "deploy"
INSTALL = ROOT / "scripts" / "install-deps.sh"
COMPOSE = DEPLOY / "compose.yaml"
K8S = DEPLOY / "k8s"
DOCKER = DEPLOY / "docker"
ENTRYPOINT = DOCKER / "worker-entrypoint.sh"
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


def _deployment_section(readme: str) -> str:
    start = readme.index("\n## Deployment\n")
    end = readme.find("\n## ", start + 1)
    return readme[start : end if end > 0 else None]


# ------------------------------------------------------------------------ set-up script
def test_install_script_groups_resolve_in_debian():
    assert _run(["bash", "-n", str(INSTALL)]).returncode == 0
    groups = {g: _group(g) for g in ("build", "web", "runtime-server", "runtime-worker", "deploy")}
    assert "python3" in groups["runtime-server"] and "docker-compose" in groups["deploy"]
    if shutil.which("apt-cache") is None:
        pytest.skip("not a Debian system: package names not checked")
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
    if shutil.which("dpkg") is None or shutil.which("objdump") is None:
        pytest.skip("needs dpkg and objdump")
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
    assert not any(
        op == "COPY" and "--from=build" not in rest and "/src" in rest for op, rest in final
    )
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
    }
    # `exec`: the worker replaces the shell, so it is PID 1 in a container and gets SIGTERM.
    out = _run(["sh", "-c", f'echo "pid=$$"; exec {ENTRYPOINT} --prefetch 2'], env=env).stdout
    lines = out.splitlines()
    assert lines[0] == lines[1], "the entrypoint must exec the worker"
    args = [line[4:] for line in lines if line.startswith("arg=")]
    assert args == [
        "connect", "--server", "server:50051", "--threads", "6",
        "--token", "s3cret with spaces", "--id", "w-7", "--prefetch", "2",
    ]  # fmt: skip
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
    proc = subprocess.Popen(
        [str(ENTRYPOINT)],
        env={**env, "RENDERFARM_SERVER": "127.0.0.1:1", "RENDERFARM_WORKER_ID": "entrypoint"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        import time

        time.sleep(1.0)
        assert proc.poll() is None, proc.stdout.read()
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
    assert set(services) == {"postgres", "server", "worker", "prometheus", "grafana"}
    for name, svc in services.items():
        assert svc.get("restart") == "unless-stopped", name
        assert "healthcheck" in svc, f"{name} has no health check"
    assert "postgres-data" in compose_config["volumes"]
    assert any(v.startswith("postgres-data:") for v in services["postgres"]["volumes"])
    # `up --scale worker=N`: nothing in the worker that only one container can have.
    worker = services["worker"]
    assert "container_name" not in worker and "ports" not in worker
    assert worker["environment"]["RENDERFARM_SERVER"] == "server:50051"
    assert worker["depends_on"]["server"]["condition"] == "service_healthy"
    server = services["server"]
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


def test_compose_settings_are_environment_variables_documented_in_the_readme(compose_config):
    text = COMPOSE.read_text()
    variables = set(re.findall(r"\$\{(\w+)", text))
    assert {"RENDERFARM_DB_PASSWORD", "RENDERFARM_WORKER_THREADS"} <= variables
    readme = (ROOT / "README.md").read_text()
    section = _deployment_section(readme)
    example = (DEPLOY / "env.example").read_text()
    for var in variables:
        assert f"`{var}`" in section, f"{var} is not documented in README, Deployment"
        assert var in example, f"{var} is not in deploy/env.example"
    # With everything at its default, the server gets exactly the server defaults.
    from renderfarm.config import Settings

    env = compose_config["services"]["server"]["environment"]
    defaults = Settings()
    for key, value in env.items():
        field = key.removeprefix("RENDERFARM_").lower()
        if field in ("database_url", "http_host", "grpc_host", "worker_token", "admin_token"):
            continue
        assert float(value) == float(getattr(defaults, field)), key


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
    assert server["static_configs"][0]["targets"] == ["server:8080"]
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


@pytest.mark.parametrize("overlay", ["external-db", "cloudnative-pg"])
def test_kubernetes_manifests_build_and_validate_offline(k8s_tree, overlay):
    import base64

    import kubernetes_validate as kv

    docs = _build(k8s_tree, overlay)
    kinds = sorted(f"{d['kind']}/{d['metadata']['name']}" for d in docs)
    expected = {
        "Namespace/renderfarm", "Deployment/renderfarm-server", "Service/renderfarm-server",
        "Deployment/renderfarm-worker", "PodDisruptionBudget/renderfarm-worker",
        "ScaledObject/renderfarm-worker",
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
    server = by[("Deployment", "renderfarm-server")]["spec"]
    worker = by[("Deployment", "renderfarm-worker")]["spec"]
    # Every Secret and ConfigMap referenced exists in the build (or is the operator's).
    for deployment in (server, worker):
        for kind, name, key in _env_refs(deployment["template"]["spec"]):
            assert (kind, name) in objects | generated, f"{kind} {name} is not defined"
            if (kind, name) in by and key is not None:
                data = by[(kind, name)].get("data", {})
                assert key in data, f"{kind} {name} has no key {key}"
    secrets = next(d for d in docs if d["kind"] == "Secret")
    decoded = {k: base64.b64decode(v).decode() for k, v in secrets["data"].items()}
    assert decoded["RENDERFARM_WORKER_TOKEN"] == "tok"
    server_env = {e["name"]: e for e in server["template"]["spec"]["containers"][0]["env"]}
    url_ref = server_env["RENDERFARM_DATABASE_URL"]["valueFrom"]["secretKeyRef"]
    if overlay == "cloudnative-pg":
        assert (url_ref["name"], url_ref["key"]) == ("renderfarm-db-app", "uri")
        assert by[("Cluster", "renderfarm-db")]["spec"]["bootstrap"]["initdb"]["database"]
    else:
        assert decoded["RENDERFARM_DATABASE_URL"].startswith("postgresql://")

    # The server: one replica, never two at once; probes on gRPC health, /healthz, /readyz.
    assert server["replicas"] == 1 and server["strategy"]["type"] == "Recreate"
    c = server["template"]["spec"]["containers"][0]
    ports = {p["name"]: p["containerPort"] for p in c["ports"]}
    assert c["livenessProbe"]["grpc"]["port"] == ports["grpc"]
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert c["startupProbe"]["httpGet"]["path"] == "/healthz"
    config = next(d for d in docs if d["kind"] == "ConfigMap")["data"]
    assert int(config["RENDERFARM_HTTP_PORT"]) == ports["http"]
    assert int(config["RENDERFARM_GRPC_PORT"]) == ports["grpc"]
    assert config["RENDERFARM_HTTP_HOST"] == config["RENDERFARM_GRPC_HOST"] == "0.0.0.0"
    service = by[("Service", "renderfarm-server")]["spec"]
    labels = server["template"]["metadata"]["labels"]
    assert all(labels.get(k) == v for k, v in service["selector"].items())
    assert {p["targetPort"] for p in service["ports"]} == {"http", "grpc"}
    from renderfarm.config import Settings

    Settings(**{k.removeprefix("RENDERFARM_").lower(): v for k, v in config.items()})

    # The workers: resource requests, a preStop drain, the server's Service as their server.
    w = worker["template"]["spec"]
    wc = w["containers"][0]
    assert wc["resources"]["requests"]["cpu"] and wc["resources"]["requests"]["memory"]
    assert "kill -TERM 1" in " ".join(wc["lifecycle"]["preStop"]["exec"]["command"])
    assert w["terminationGracePeriodSeconds"] >= 60
    wenv = {e["name"]: e for e in wc["env"]}
    assert wenv["RENDERFARM_SERVER"]["value"] == f"renderfarm-server:{ports['grpc']}"
    pdb = by[("PodDisruptionBudget", "renderfarm-worker")]["spec"]
    wlabels = worker["template"]["metadata"]["labels"]
    assert all(wlabels.get(k) == v for k, v in pdb["selector"]["matchLabels"].items())
    assert "renderfarm_queue_depth" in _scaledobject_queries()[0]


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


def test_readme_documents_each_deployment_step():
    readme = (ROOT / "README.md").read_text()
    section = _deployment_section(readme)
    for command in (
        "docker compose -f deploy/compose.yaml up",
        "--scale worker=",
        "kubectl apply -k deploy/k8s/overlays/external-db",
        "kubectl apply -k deploy/k8s/overlays/cloudnative-pg",
        "deploy/netns/farm.sh up",
        "make test-deploy",
    ):
        assert command in section, command
    # Commands shown in the README's examples name files that exist.
    for path in re.findall(r"deploy/[\w./-]+", section):
        path = path.rstrip(".")
        assert (ROOT / path).exists() or path.endswith(("secrets.env", "/.env")), path
