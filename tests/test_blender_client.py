"""The Blender add-on's REST client (integrations/blender/renderfarm_blender/client.py: the
standard library only, no bpy) against a real farm over https with a private CA: the CA file,
an untrusted certificate, the farm's refusals with their field, an unreachable farm."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from renderfarm.cli.localfarm import LocalFarm, free_port
from renderfarm.client import Client

from .tlshelpers import make_pki

CLIENT = Path(__file__).resolve().parents[1] / "integrations/blender/renderfarm_blender/client.py"
TOKEN = "rf_blender-client-test-1b9d"


def _load():
    # The file alone: the package's __init__ imports bpy, which this environment has not.
    spec = importlib.util.spec_from_file_location("renderfarm_blender_client", CLIENT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


addon = _load()


@pytest.fixture(scope="module")
def tls_farm(tmp_path_factory, worker_binary):
    directory = tmp_path_factory.mktemp("blender-tls")
    pki = make_pki(directory)
    env = {
        "RENDERFARM_TLS_CERT_FILE": pki.server_cert,
        "RENDERFARM_TLS_KEY_FILE": pki.server_key,
        "RENDERFARM_ADMIN_TOKEN": TOKEN,
    }
    with LocalFarm(workers=0, data_dir=directory / "farm", env=env, ca_file=pki.ca) as farm:
        yield farm, pki


def test_https_with_the_ca_file(tls_farm):
    farm, pki = tls_farm
    assert farm.url.startswith("https://127.0.0.1:")
    docs = addon.FarmClient(farm.url, TOKEN, pki.ca, 30).settings()
    with Client(farm.url, token=TOKEN, ca_file=pki.ca) as reference:
        assert docs == reference.http.get("/api/v1/settings").json()


def test_untrusted_certificate_says_to_set_the_ca_file(tls_farm):
    farm, _ = tls_farm
    with pytest.raises(addon.FarmError) as e:
        addon.FarmClient(farm.url, TOKEN, "", 30).settings()  # the system's CAs: not ours
    assert e.value.status == 0
    assert "certificate is not trusted" in e.value.report() and "CA file" in e.value.report()


def test_unreadable_ca_file(tmp_path):
    with pytest.raises(addon.FarmError, match="cannot read the CA file"):
        addon.FarmClient("https://127.0.0.1:1", "", str(tmp_path / "missing.pem"))


def test_refusals_carry_status_message_and_field(tls_farm):
    farm, pki = tls_farm
    client = addon.FarmClient(farm.url, TOKEN, pki.ca, 30)
    with pytest.raises(addon.FarmError) as e:
        client.submit(b"not a scene", "scene.glb", {"max_spp": 4}, "junk")
    assert e.value.status == 400 and e.value.field.startswith("scene")
    assert e.value.report().startswith("the farm refused (HTTP 400): ")
    assert e.value.report().endswith(f"[{e.value.field}]")
    with pytest.raises(addon.FarmError) as e:
        client.submit(b"glTF", "scene.glb", {"max_spp": 0}, "junk")
    assert (e.value.status, e.value.field) == (400, "settings.max_spp")
    with pytest.raises(addon.FarmError) as e:
        client.job("0123456789ab")
    assert e.value.status == 404
    with pytest.raises(addon.FarmError) as e:
        addon.FarmClient(farm.url, "wrong", pki.ca, 30).settings()
    assert e.value.status == 401 and "set the API token" in e.value.report()


def test_unreachable_farm_and_bad_url():
    port = free_port()  # nothing listens on it
    with pytest.raises(
        addon.FarmError, match=r"connection refused by .* \(is the farm running\?\)"
    ):
        addon.FarmClient(f"http://127.0.0.1:{port}", "", "", 5).settings()
    with pytest.raises(addon.FarmError, match="farm URL must be"):
        addon.FarmClient("127.0.0.1:8080")
