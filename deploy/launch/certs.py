"""`vamppi certs DIR`: a local certificate authority and one certificate per role (and
instance), for mutual TLS between every client and router (common.security).

Made with the `openssl` command line (nothing is downloaded): an EC P-256 CA, and for each
certificate a key, a request and the CA's signature. The common name is the certificate's
name (a role, or `role-instance`), which the routers' access-control rules match; the
organisational unit names the instance. Every certificate is valid for both ends of a
link (serverAuth and clientAuth) and for the names in `hosts` (loopback by default; a
router's address across machines). Keys are written 0600.

`revoke(dir, name)`: zenoh checks no revocation list, so a router accepts only the names
issued in its directory and not listed in `revoked.txt` (common.security.accepted_names);
a revoked certificate still completes TLS, and every message it sends is denied once
the routers are restarted with the list: docs/security.md.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from common.security import REVOKED, ROLES, accepted_names, revoked_names, role_of

DAYS = 365


class CertError(RuntimeError):
    """The certificates could not be made (no openssl, a bad name, a failed command)."""


def _run(*args: str) -> None:
    r = subprocess.run(["openssl", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {r.stderr.strip()[-500:]}")


def make_certs(out: str | Path, names: tuple[str, ...] = ROLES,
               hosts: tuple[str, ...] = ("localhost", "127.0.0.1"), days: int = DAYS
               ) -> list[Path]:
    """The CA (`ca.pem`, `ca.key`, made once and kept) and a certificate per name in
    `out`: `role` or `role-instance`, common name the role. The written certificates."""
    if shutil.which("openssl") is None:
        raise CertError("the openssl command is not installed")
    d = Path(out)
    d.mkdir(parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    ca_key, ca = d / "ca.key", d / "ca.pem"
    if not ca.exists():
        _run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", str(ca_key), "-out", str(ca), "-days", str(days),
             "-subj", "/CN=vamppi-ca")
        os.chmod(ca_key, 0o600)
    sans = ",".join(f"IP:{h}" if h.replace(".", "").isdigit() or ":" in h else f"DNS:{h}"
                    for h in hosts)
    made = []
    revoked = revoked_names(d)
    for name in names:
        role, _, instance = name.partition("-")
        if role not in ROLES or not all(c.isalnum() or c in "_." for c in instance):
            raise CertError(f"{name!r}: a role ({', '.join(ROLES)}), optionally -instance")
        if name in revoked:
            raise CertError(f"{name!r} is revoked ({d / REVOKED}): issue another name")
        key, pem = d / f"{name}.key", d / f"{name}.pem"
        with tempfile.TemporaryDirectory() as tmp:
            csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
            ext.write_text(f"subjectAltName={sans}\nbasicConstraints=CA:FALSE\n"
                           "keyUsage=digitalSignature,keyEncipherment\n"
                           "extendedKeyUsage=serverAuth,clientAuth\n")
            _run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                 "-keyout", str(key), "-out", str(csr),
                 "-subj", f"/CN={name}/OU={instance or '0'}")
            os.chmod(key, 0o600)
            _run("x509", "-req", "-in", str(csr), "-CA", str(ca), "-CAkey", str(ca_key),
                 "-CAcreateserial", "-out", str(pem), "-days", str(days), "-extfile", str(ext))
        made.append(pem)
    return made


def ensure_certs(out: str | Path) -> Path:
    """`out` holding a CA and a certificate per role, made now if it does not (`vamppi up`
    on first use). Made in a directory beside it and renamed into place, so that two
    launchers starting at once never see half of it."""
    d = Path(out).expanduser()
    wanted = [n for n in ROLES if n not in revoked_names(d)]
    if all((d / f"{n}.pem").exists() for n in ("ca", *wanted)):
        return d
    d.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".certs-", dir=d.parent))
    make_certs(tmp)
    try:
        tmp.rename(d)
    except OSError:                   # another launcher's landed first, or a partial one
        if not (d / "ca.pem").exists():
            raise CertError(f"{d} exists without a CA: remove it or name another "
                            "(bus.certs)") from None
        shutil.rmtree(tmp, ignore_errors=True)
        make_certs(d, tuple(n for n in wanted if not (d / f"{n}.pem").exists()))
    return d


def revoke(out: str | Path, name: str) -> list[str]:
    """List `name` in the directory's `revoked.txt` and delete its key and certificate; the
    names its routers accept from then on (restart them to apply)."""
    d = Path(out).expanduser()
    if not (d / "ca.pem").exists() or role_of(name) not in ROLES:
        raise CertError(f"{name!r}: not a certificate name of {d}")
    if name not in revoked_names(d):
        with open(d / REVOKED, "a") as f:
            f.write(name + "\n")
    for ext in ("pem", "key"):
        (d / f"{name}.{ext}").unlink(missing_ok=True)
    return list(accepted_names(d))
