"""`teleop serve --https` / `--tls-cert FILE --tls-key FILE`: every page and websocket of the session over TLS.

WebXR (the XR page) and a phone's sensors need a secure context: `http://localhost` is one, a LAN address over
http is not. `--https` makes a self-signed certificate on first use (the `openssl` command; EC P-256, valid for
localhost, 127.0.0.1 and this machine's name, 825 days) and keeps it, 0600 in a 0700 folder, in the user's
config folder (`$XDG_CONFIG_HOME/mujoco-teleop/tls/`, default ~/.config); its SHA-256 fingerprint is printed,
so the warning a browser shows for it can be checked against it. `--tls-cert` / `--tls-key` take the user's own.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import socket
import ssl
import subprocess
import sys
import tempfile
from pathlib import Path

from teleop.errors import UsageError

CERT_DAYS = 825


def add_tls_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--https", action="store_true",
                   help="serve every page and websocket over TLS with a self-signed certificate made on first use "
                        "(kept 0600 in ~/.config/mujoco-teleop/tls; its SHA-256 fingerprint is printed): a headset "
                        "or phone on Wi-Fi needs a secure context")
    p.add_argument("--tls-cert", type=Path, default=None, metavar="FILE", help="serve over TLS with this PEM certificate")
    p.add_argument("--tls-key", type=Path, default=None, metavar="FILE", help="the PEM private key of --tls-cert")


def tls_folder() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "mujoco-teleop" / "tls"


def fingerprint(cert: Path) -> str:
    """The certificate's SHA-256 fingerprint, as browsers show it (AB:CD:...)."""
    der = ssl.PEM_cert_to_DER_cert(cert.read_text(encoding="ascii"))
    return ":".join(f"{b:02X}" for b in hashlib.sha256(der).digest())


def self_signed(folder: Path | None = None) -> tuple[Path, Path, bool]:
    """(cert, key, made now): the kept self-signed pair, made with `openssl` when missing."""
    folder = tls_folder() if folder is None else folder
    cert, key = folder / "cert.pem", folder / "key.pem"
    if cert.is_file() and key.is_file():
        return cert, key, False
    openssl = shutil.which("openssl")
    if openssl is None:
        raise UsageError("--https makes its certificate with the openssl command, which is not installed "
                         "(Debian: apt-get install openssl), or give your own with --tls-cert FILE --tls-key FILE")
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    names = ["DNS:localhost", "IP:127.0.0.1", "IP:::1"]
    host = socket.gethostname()
    if host and host != "localhost":
        names.append(f"DNS:{host}")
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        new_cert, new_key = Path(tmp) / "cert.pem", Path(tmp) / "key.pem"
        done = subprocess.run([openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                               "-keyout", str(new_key), "-out", str(new_cert), "-days", str(CERT_DAYS),
                               "-subj", "/CN=mujoco-teleop", "-addext", "subjectAltName=" + ",".join(names)],
                              capture_output=True, text=True, timeout=60)
        if done.returncode != 0:
            raise UsageError(f"--https: openssl could not make a certificate: {(done.stderr.strip().splitlines() or ['?'])[-1]}")
        for path in (new_cert, new_key):
            os.chmod(path, 0o600)
        os.replace(new_key, key)
        os.replace(new_cert, cert)
    return cert, key, True


def tls_files(args: argparse.Namespace) -> tuple[Path | None, Path | None]:
    """The (cert, key) the flags ask for (None, None: plain http); --https prints where its pair is and its fingerprint."""
    if args.https and (args.tls_cert is not None or args.tls_key is not None):
        raise UsageError("--https makes its own certificate; --tls-cert / --tls-key give yours: use one or the other")
    if args.tls_cert is not None or args.tls_key is not None:
        if args.tls_cert is None or args.tls_key is None:
            raise UsageError("--tls-cert and --tls-key go together: give both")
        for flag, path in (("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
            if not path.is_file():
                raise UsageError(f"{flag} {path}: no such file")
        return args.tls_cert, args.tls_key
    if not args.https:
        return None, None
    cert, key, made = self_signed()
    print(f"{'made' if made else 'using'} the self-signed certificate {cert} (SHA-256 {fingerprint(cert)}); "
          "a browser warns once: check the fingerprint, then accept it", file=sys.stderr)
    return cert, key
