"""`teleop serve --https`: every page and websocket over TLS with a self-signed certificate made on first use,
kept 0600 in the user's config folder, its SHA-256 fingerprint printed (what a headset on Wi-Fi needs for WebXR)."""

from __future__ import annotations

import ssl
import urllib.error
import stat
import urllib.request

import pytest
from websockets.sync.client import connect

import tests.browser as headless
from teleop.cli.tls_args import fingerprint
from teleop.web.xr_page.scene_message import read_scene_header
from tests.support import assert_one_line_error, run_cli

pytestmark = pytest.mark.e2e
TOKEN = "xr-secret-token"


def test_https_serves_the_pages_and_websockets_over_tls_with_the_made_certificate(tmp_path):
    config = tmp_path / "config"
    proc = headless.ServeProcess(["--https", "--device", "gizmo", "--token", TOKEN], tmp_path,
                                 env={"XDG_CONFIG_HOME": str(config)})
    try:
        folder = config / "mujoco-teleop" / "tls"
        cert, key = folder / "cert.pem", folder / "key.pem"
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700
        assert stat.S_IMODE(cert.stat().st_mode) == 0o600 and stat.S_IMODE(key.stat().st_mode) == 0o600
        assert fingerprint(cert) in proc.log() and len(fingerprint(cert)) == 95
        assert proc.status()["url"].startswith("https://")
        trusted = ssl.create_default_context(cafile=str(cert))  # the made certificate, and nothing else, is trusted
        base = f"https://localhost:{proc.port}"
        printed = f"XR headset: open https://127.0.0.1:{proc.port}/xr?token={TOKEN} in the headset's browser"
        assert printed in proc.log()
        with pytest.raises(urllib.error.HTTPError) as refused:  # the same token rules as the session page
            urllib.request.urlopen(base + "/xr", context=trusted, timeout=30)
        assert refused.value.code == 403
        assert b"Enter VR" in urllib.request.urlopen(f"{base}/xr?token={TOKEN}", context=trusted, timeout=30).read()
        assert urllib.request.urlopen(f"{base}/?token={TOKEN}", context=trusted, timeout=30).status == 200
        with connect(f"wss://localhost:{proc.port}/teleop/xr?token={TOKEN}", ssl=trusted, open_timeout=30) as ws:
            assert read_scene_header(ws.recv(timeout=30))["arms"] == 1
        with pytest.raises(urllib.error.URLError):  # another certificate (the system's roots) does not vouch for it
            urllib.request.urlopen(f"{base}/xr?token={TOKEN}", context=ssl.create_default_context(), timeout=30)
    finally:
        proc.stop()
    made = cert.read_bytes()
    again = headless.ServeProcess(["--https", "--device", "gizmo"], tmp_path, env={"XDG_CONFIG_HOME": str(config)})
    again.stop()
    assert cert.read_bytes() == made, "kept, not made again"


def test_tls_flags_that_contradict_are_one_line_errors(tmp_path):
    assert_one_line_error(run_cli("serve", "--tls-cert", str(tmp_path / "c.pem")), "--tls-cert and --tls-key")
    assert_one_line_error(run_cli("serve", "--https", "--tls-cert", "a", "--tls-key", "b"), "--https")
