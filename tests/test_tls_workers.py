"""C++ workers join a TLS farm (`renderfarm-worker connect --tls --ca-file`), optionally with
client certificates (mutual TLS), and render the same image as on a plaintext farm."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .apihelpers import TINY
from .conftest import CORNELL
from .tlshelpers import make_pki
from .waiting import wait_until

SETTINGS = {**TINY, "width": 48, "height": 48, "max_spp": 8, "seed": 11}


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    return make_pki(tmp_path_factory.mktemp("pki"))


def _render(farm: LocalFarm) -> tuple[dict[str, list[float]], bytes]:
    """The job's EXR channels (the file's header carries its creation time) and PNG bytes."""
    with Client(farm.url, ca_file=farm.ca_file) as client:
        job = client.submit(CORNELL, settings=SETTINGS, name="tls")
        done = client.wait(job["id"], timeout_s=180)
        assert done["state"] == "completed", done
        exr = Path(farm.data_dir) / "result.exr"
        exr.write_bytes(client.image(job["id"], "exr"))
        channels = {name: values.ravel().tolist() for name, values in read_exr(str(exr)).items()}
        return channels, client.image(job["id"], "png")


@pytest.fixture(scope="module")
def plaintext_image(tmp_path_factory):
    with LocalFarm(workers=1, threads=1, data_dir=tmp_path_factory.mktemp("plain")) as farm:
        return _render(farm)


def _tls_env(pki, mutual: bool) -> dict[str, str]:
    env = {"RENDERFARM_TLS_CERT_FILE": pki.server_cert, "RENDERFARM_TLS_KEY_FILE": pki.server_key}
    if mutual:
        env["RENDERFARM_TLS_CLIENT_CA_FILE"] = pki.ca
    return env


def test_a_tls_farm_renders_the_plaintext_farms_image(tmp_path, pki, plaintext_image):
    farm = LocalFarm(workers=1, threads=1, data_dir=tmp_path, env=_tls_env(pki, False),
                     worker_args=["--ca-file", pki.ca], ca_file=pki.ca)  # fmt: skip
    with farm:
        assert _render(farm) == plaintext_image
        log = next(tmp_path.glob("worker-*.log")).read_text()
        assert "over TLS" in log, log


def test_mutual_tls_admits_only_workers_with_the_cas_certificate(tmp_path, pki, plaintext_image):
    good = ["--ca-file", pki.ca, "--cert", pki.client_cert, "--key", pki.client_key]
    farm = LocalFarm(workers=1, threads=1, data_dir=tmp_path, env=_tls_env(pki, True),
                     worker_args=good, ca_file=pki.ca)  # fmt: skip
    with farm:
        # Two workers that must stay out: no certificate, and one the CA did not sign.
        farm.worker_args = ["--ca-file", pki.ca]
        farm.add_workers(1, threads=1)
        farm.add_workers(1, threads=1, extra_args=["--cert", pki.stranger_cert,
                                                    "--key", pki.stranger_key])  # fmt: skip
        assert _render(farm) == plaintext_image
        with Client(farm.url, ca_file=pki.ca) as client:
            ids = [w["id"] for w in client.workers()]
        assert ids == [f"{socket.gethostname()}-local-0"], ids
        # The refused workers kept trying (and said why in their logs) rather than exiting.
        for index in (1, 2):
            log = tmp_path / f"worker-{index}.log"
            wait_until(lambda log=log: "reconnecting" in log.read_text(), timeout_s=60,
                       what=f"worker {index} to report its refused connection")  # fmt: skip
            assert farm.worker_procs[index].poll() is None


def test_worker_tls_flags_are_checked_before_connecting(tmp_path, worker_binary):
    import subprocess

    missing = tmp_path / "missing.pem"
    for args, words in [
        (["--ca-file", str(missing)], "cannot read the file"),
        (["--cert", str(missing)], "--cert and --key go together"),
    ]:
        done = subprocess.run(
            [worker_binary, "connect", "--server", "127.0.0.1:1", *args],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert done.returncode == 2 and words in done.stderr, done.stderr
