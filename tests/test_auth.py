"""Security: API tokens (none, wrong, another owner's job, revoked), admin tokens, the worker
token, refusing to listen beyond loopback without tokens, and TLS for REST and gRPC."""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import ssl
import subprocess
import sys

import grpc
import httpx
import pytest

from renderfarm.cli.localfarm import LocalFarm, free_port
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc, workers_pb2, workers_pb2_grpc

from .apihelpers import TINY, Apis, Error, cornell_glb, create_token
from .waiting import wait_until

CLI = [sys.executable, "-m", "renderfarm"]
WORKER_TOKEN = "worker-secret-for-tests"


_token = create_token


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    """A farm with three tokens (alice, bob, admin) and a worker token; no workers."""
    data = tmp_path_factory.mktemp("secured")
    tokens = {name: _token(data, name, admin=name == "root") for name in ("alice", "bob", "root")}
    farm = LocalFarm(workers=0, data_dir=data, env={"RENDERFARM_WORKER_TOKEN": WORKER_TOKEN})
    with farm:
        apis = {name: Apis(farm.url, farm.grpc_address, t["token"]) for name, t in tokens.items()}
        apis["nobody"] = Apis(farm.url, farm.grpc_address, None)
        apis["wrong"] = Apis(farm.url, farm.grpc_address, "rf_not-a-real-token")
        yield farm, tokens, apis
        for a in apis.values():
            a.close()


def test_tokens_are_listed_but_only_their_hashes_are_stored(secured):
    farm, tokens, _ = secured
    done = subprocess.run(CLI + ["token", "ls", "--json", "--data-dir", str(farm.data_dir)],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    listed = json.loads(done.stdout)
    assert {t["name"] for t in listed} >= {"alice", "bob", "root"}
    assert all("token" not in t for t in listed)
    assert [t["admin"] for t in listed if t["name"] == "root"] == [True]


@pytest.mark.parametrize("who", ["nobody", "wrong"])
def test_requests_without_a_valid_token_are_refused_by_both_apis(secured, who):
    _, _, apis = secured
    a = apis[who]
    rest = a.rest("GET", "/api/v1/jobs")
    rpc = a.rpc("ListJobs", jobs_pb2.ListJobsRequest())
    assert isinstance(rest, Error) and isinstance(rpc, Error)
    assert rest.kind == rpc.kind == "unauthenticated"
    assert rest.field == rpc.field == "authorization"
    r = a.http.post("/api/v1/jobs", json={"scene_sha256": "0" * 64})
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    submit = a.submit_rpc(cornell_glb(), "c.glb", TINY, "x")
    assert submit.kind == "unauthenticated"


def test_jobs_belong_to_their_token_and_others_cannot_touch_them(secured):
    _, _, apis = secured
    alice, bob, root = apis["alice"], apis["bob"], apis["root"]
    job = alice.submit_rest(cornell_glb(), "c.glb", TINY, "alice's")
    assert job["owner"] == "alice"
    via_grpc = alice.submit_rpc(cornell_glb(), "c.glb", TINY, "alice's too")
    assert via_grpc["owner"] == "alice"
    jid = job["id"]
    refused_rest = [
        bob.rest("GET", f"/api/v1/jobs/{jid}"),
        bob.rest("POST", f"/api/v1/jobs/{jid}/cancel"),
        bob.rest("DELETE", f"/api/v1/jobs/{jid}"),
        bob.rest("GET", f"/api/v1/jobs/{jid}/image.png"),
        bob.rest("GET", f"/api/v1/jobs/{jid}/events"),
        bob.rest("GET", f"/api/v1/jobs/{jid}/convergence"),
        bob.rest("GET", f"/api/v1/jobs/{jid}/watch"),
        bob.rest("POST", f"/api/v1/jobs/{jid}/pause"),
        bob.rest("POST", f"/api/v1/jobs/{jid}/resume"),
        bob.rest("POST", f"/api/v1/jobs/{jid}/retry"),
        bob.rest("POST", f"/api/v1/jobs/{jid}/continue", json={"settings": {"max_spp": 64}}),
        bob.rest("PATCH", f"/api/v1/jobs/{jid}", json={"priority": 5}),
    ]
    refused_rpc = [
        bob.rpc("GetJob", jobs_pb2.GetJobRequest(job_id=jid)),
        bob.rpc("CancelJob", jobs_pb2.CancelJobRequest(job_id=jid)),
        bob.rpc("DeleteJob", jobs_pb2.DeleteJobRequest(job_id=jid)),
        bob.rpc("GetImage", jobs_pb2.GetImageRequest(job_id=jid)),
        bob.watch_rpc(jid),
        bob.rpc("PauseJob", jobs_pb2.PauseJobRequest(job_id=jid)),
        bob.rpc("ResumeJob", jobs_pb2.ResumeJobRequest(job_id=jid)),
        bob.rpc("RetryJob", jobs_pb2.RetryJobRequest(job_id=jid)),
        bob.rpc("UpdateJob", jobs_pb2.UpdateJobRequest(job_id=jid, priority=5)),
        bob.rpc("ContinueJob", jobs_pb2.ContinueJobRequest(job_id=jid)),
    ]
    for answer in refused_rest + refused_rpc:
        assert isinstance(answer, Error) and answer.kind == "forbidden", answer
    listed_by_bob = {j["id"] for j in bob.rest("GET", "/api/v1/jobs")["jobs"]}
    assert jid not in listed_by_bob
    assert jid in {j["id"] for j in alice.rest("GET", "/api/v1/jobs")["jobs"]}
    # An admin sees and may cancel every owner's jobs; the job still belongs to alice.
    assert jid in {j["id"] for j in root.rest("GET", "/api/v1/jobs")["jobs"]}
    assert root.rest("GET", f"/api/v1/jobs/{jid}")["owner"] == "alice"
    # Bob's job control changed nothing; alice's own and an admin's do.
    assert root.rest("GET", f"/api/v1/jobs/{jid}")["settings"]["priority"] == 0
    assert alice.rest("POST", f"/api/v1/jobs/{jid}/pause")["state"] == "paused"
    assert (
        root.rest("PATCH", f"/api/v1/jobs/{jid}", json={"priority": 7})["settings"]["priority"] == 7
    )
    assert root.rest("POST", f"/api/v1/jobs/{jid}/cancel")["state"] == "cancelled"
    assert alice.rest("DELETE", f"/api/v1/jobs/{jid}") is None
    assert bob.rest("GET", "/api/v1/whoami") == {"owner": "bob", "admin": False}


def test_a_revoked_token_stops_working(secured, tmp_path):
    farm, _, apis = secured
    spare = _token(farm.data_dir, "spare")
    a = Apis(farm.url, farm.grpc_address, spare["token"])
    try:
        wait_until(
            lambda: not isinstance(a.rest("GET", "/api/v1/whoami"), Error),
            10,
            "the new token to be accepted",
            poll_s=0.2,
        )
        done = subprocess.run(
            CLI + ["token", "revoke", spare["id"], "--data-dir", str(farm.data_dir)],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert done.returncode == 0 and "revoked" in done.stdout, done.stderr
        # The server trusts its token cache for 2 s.
        wait_until(
            lambda: isinstance(a.rest("GET", "/api/v1/whoami"), Error),
            10,
            "the revoked token to be refused",
            poll_s=0.2,
        )
        rest = a.rest("GET", "/api/v1/jobs")
        rpc = a.rpc("ListJobs", jobs_pb2.ListJobsRequest())
        assert rest.kind == rpc.kind == "unauthenticated"
        assert "revoked" in rest.message and "revoked" in rpc.message
    finally:
        a.close()


def test_workers_need_the_worker_token(secured):
    farm, _, _ = secured
    with grpc.insecure_channel(farm.grpc_address) as channel:
        stub = workers_pb2_grpc.WorkerServiceStub(channel)
        for token in ("", "wrong"):
            hello = workers_pb2.WorkerMessage(
                hello=workers_pb2.Hello(worker_id="intruder", cores=1, token=token)
            )
            with pytest.raises(grpc.RpcError) as refused:
                next(iter(stub.Connect(iter([hello]), timeout=10)))
            assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
        hello = workers_pb2.WorkerMessage(
            hello=workers_pb2.Hello(worker_id="welcome", cores=1, token=WORKER_TOKEN)
        )
        first = next(iter(stub.Connect(iter([hello]), timeout=10)))
        assert first.welcome.worker_id == "welcome"


def test_a_session_cookie_stands_in_for_the_bearer_header(secured):
    """The dashboard's sign-in: POST /api/v1/session checks the token and sets an HttpOnly
    SameSite=Strict cookie that authorizes requests without a header; DELETE clears it."""
    farm, tokens, _ = secured
    with httpx.Client(base_url=farm.url, timeout=30) as http:
        bad = http.post("/api/v1/session", json={"token": "rf_not-a-real-token"})
        assert bad.status_code == 401 and bad.json()["field"] == "authorization"
        assert "set-cookie" not in bad.headers and not http.cookies
        assert http.post("/api/v1/session", json={"token": ""}).status_code == 401
        assert not http.cookies
        assert http.get("/api/v1/whoami").status_code == 401

        good = http.post("/api/v1/session", json={"token": tokens["alice"]["token"]})
        assert good.status_code == 200 and good.json() == {"owner": "alice", "admin": False}
        cookie = good.headers["set-cookie"]
        assert cookie.startswith(f"renderfarm_token={tokens['alice']['token']};")
        attributes = {a.strip().lower() for a in cookie.split(";")[1:]}
        assert {"httponly", "samesite=strict", "path=/"} <= attributes
        assert "secure" not in attributes  # plain http; Secure is set over TLS

        # Only the cookie: authorized as alice, also for the job list and the stream's path.
        assert http.get("/api/v1/whoami").json() == {"owner": "alice", "admin": False}
        assert http.get("/api/v1/jobs").status_code == 200
        # A header still wins over the cookie.
        other = {"Authorization": f"Bearer {tokens['bob']['token']}"}
        assert http.get("/api/v1/whoami", headers=other).json()["owner"] == "bob"
        wrong = {"Authorization": "Bearer rf_not-a-real-token"}
        assert http.get("/api/v1/whoami", headers=wrong).status_code == 401

        out = http.delete("/api/v1/session")
        assert out.status_code == 204
        assert "renderfarm_token=" in out.headers["set-cookie"]
        assert not http.cookies
        assert http.get("/api/v1/whoami").status_code == 401


def test_an_admin_token_from_the_environment_turns_auth_on(tmp_path):
    env = {"RENDERFARM_ADMIN_TOKEN": "rf_configured-admin-secret"}
    with LocalFarm(workers=0, data_dir=tmp_path / "d", env=env) as farm:
        anonymous = Apis(farm.url, farm.grpc_address)
        admin = Apis(farm.url, farm.grpc_address, env["RENDERFARM_ADMIN_TOKEN"])
        try:
            assert anonymous.rest("GET", "/api/v1/jobs").kind == "unauthenticated"
            assert admin.rest("GET", "/api/v1/whoami") == {"owner": "admin", "admin": True}
        finally:
            anonymous.close()
            admin.close()


def test_server_refuses_a_public_address_without_tokens(tmp_path):
    done = subprocess.run(
        CLI + ["server", "--data-dir", str(tmp_path / "d"), "--http-host", "0.0.0.0",
               "--http-port", str(free_port()), "--grpc-port", str(free_port())],
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert done.returncode == 1
    assert "refusing to listen on 0.0.0.0" in done.stderr
    assert "no API token exists" in done.stderr and "no worker token" in done.stderr


def _self_signed(directory) -> tuple[str, str]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "renderfarm test")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = directory / "cert.pem", directory / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return str(cert_path), str(key_path)


def test_tls_for_rest_and_grpc(tmp_path):
    cert, key = _self_signed(tmp_path)
    http_port, grpc_port = free_port(), free_port()
    env = {**os.environ, "RENDERFARM_TLS_CERT_FILE": cert, "RENDERFARM_TLS_KEY_FILE": key}
    log = open(tmp_path / "server.log", "wb")  # noqa: SIM115
    server = subprocess.Popen(
        CLI + ["server", "--data-dir", str(tmp_path / "d"), "--http-port", str(http_port),
               "--grpc-port", str(grpc_port)],
        stdout=log, stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    try:
        url = f"https://127.0.0.1:{http_port}"
        with httpx.Client(verify=ssl.create_default_context(cafile=cert), timeout=5) as https:

            def ready() -> bool:
                assert server.poll() is None, (tmp_path / "server.log").read_text()
                try:
                    return https.get(f"{url}/readyz").status_code == 200
                except httpx.HTTPError:
                    return False

            wait_until(ready, 120, "the TLS server to be ready", poll_s=0.2)
            assert https.get(f"{url}/api/v1/jobs").json()["jobs"] == []
        with pytest.raises(httpx.HTTPError):  # plain HTTP is not served
            httpx.get(f"http://127.0.0.1:{http_port}/readyz", timeout=5)
        with pytest.raises(httpx.HTTPError):  # and the certificate is checked
            httpx.get(f"{url}/readyz", timeout=5)
        from renderfarm.client import Client

        with Client(url, ca_file=cert) as client:
            assert client.list()["jobs"] == []
        credentials = grpc.ssl_channel_credentials(root_certificates=open(cert, "rb").read())
        with grpc.secure_channel(f"127.0.0.1:{grpc_port}", credentials) as channel:
            stub = jobs_pb2_grpc.JobServiceStub(channel)
            assert list(stub.ListJobs(jobs_pb2.ListJobsRequest(), timeout=10).jobs) == []
        with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as channel:
            stub = jobs_pb2_grpc.JobServiceStub(channel)
            with pytest.raises(grpc.RpcError):
                stub.ListJobs(jobs_pb2.ListJobsRequest(), timeout=5)
    finally:
        server.terminate()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
        log.close()
