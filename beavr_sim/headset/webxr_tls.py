"""A self-signed certificate for the WebXR page on a LAN address (WebXR needs HTTPS there).

Generated on first use with the ``openssl`` command line tool (no Python dependency) and kept
in the user's cache folder (``$XDG_CACHE_HOME/beavr_sim/webxr-tls``, default
``~/.cache/beavr_sim/webxr-tls``): ``cert.pem``, ``key.pem`` (mode 0600) and ``names.json``,
the addresses the certificate names. It is made again when a host it does not name is asked
for. Delete the folder to start over; the headset's browser then asks once more to accept it.
"""

from __future__ import annotations

import ipaddress
import json
import os
import shutil
import socket
import ssl
import subprocess
import tempfile
from pathlib import Path

#: Days the certificate is valid (Safari refuses server certificates valid for longer).
VALID_DAYS = 825
COMMON_NAME = "beavr_sim WebXR (self-signed)"


def default_cert_dir() -> Path:
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "beavr_sim" / "webxr-tls"


def local_ipv4_addresses() -> list[str]:
    """This machine's IPv4 addresses as far as they can be found without a network request:
    the host name's addresses and the one the default route leaves from."""
    found: list[str] = []
    try:
        found += socket.gethostbyname_ex(socket.gethostname())[2]
    except OSError:
        pass
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: a UDP connect sends nothing
            found.append(s.getsockname()[0])
        except OSError:
            pass
    return sorted({a for a in found if not a.startswith("127.")})


def certificate_names(host: str) -> list[str]:
    """Subject alternative names for serving on ``host``: the host itself (every local IPv4
    address for ``0.0.0.0``), plus ``localhost`` and 127.0.0.1."""
    names = {"localhost", "127.0.0.1"}
    names.update(local_ipv4_addresses() if host == "0.0.0.0" else [host])
    return sorted(names)


def _san(names: list[str]) -> str:
    parts = []
    for name in names:
        try:
            ipaddress.ip_address(name)
            parts.append(f"IP:{name}")
        except ValueError:
            parts.append(f"DNS:{name}")
    return "subjectAltName=" + ",".join(parts)


def ensure_certificate(host: str, cert_dir: Path | None = None) -> tuple[Path, Path]:
    """``(cert.pem, key.pem)`` naming ``host``: the cached pair when it names every address
    needed, else a new one (``openssl req -x509``, EC P-256)."""
    folder = Path(cert_dir) if cert_dir is not None else default_cert_dir()
    cert, key, meta = folder / "cert.pem", folder / "key.pem", folder / "names.json"
    names = certificate_names(host)
    if cert.is_file() and key.is_file() and meta.is_file():
        try:
            cached = set(json.loads(meta.read_text()))
        except (ValueError, TypeError):
            cached = set()
        if set(names) <= cached:
            return cert, key
        names = sorted(cached | set(names))  # keep serving the addresses it named before
    openssl = shutil.which("openssl")
    if openssl is None:
        raise FileNotFoundError(
            "HTTPS for the WebXR page on a LAN address needs the openssl command to make a "
            "self-signed certificate: sudo apt-get install openssl (or serve on 127.0.0.1)"
        )
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        new_cert, new_key = Path(tmp) / "cert.pem", Path(tmp) / "key.pem"
        cmd = [
            openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-keyout", str(new_key), "-out", str(new_cert), "-days", str(VALID_DAYS),
            "-subj", f"/CN={COMMON_NAME}", "-addext", _san(names),
            "-addext", "basicConstraints=critical,CA:FALSE",
            "-addext", "extendedKeyUsage=serverAuth",
        ]  # fmt: skip
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
        if result.returncode != 0:
            raise OSError(f"openssl could not make the certificate: {result.stderr.strip()}")
        new_key.chmod(0o600)
        os.replace(new_key, key)
        os.replace(new_cert, cert)
    meta.write_text(json.dumps(names) + "\n")
    return cert, key


def server_ssl_context(cert: Path, key: Path) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(cert, key)
    return context
