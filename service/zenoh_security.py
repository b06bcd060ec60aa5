"""Zenoh secured by Zenoh itself: TLS (and mutual TLS) on the listen endpoints, user/password
authentication of the peers that connect, and access control on the agilegs keys.

:func:`zenoh_settings` turns the server's settings into Zenoh config entries (path -> value,
for :func:`agilegs.client.zenoh_rpc.session_config`):

- ``zenoh_tls_certificate`` / ``zenoh_tls_private_key``: the certificate the ``tls/...`` listen
  endpoints present; ``zenoh_tls_root_ca`` verifies the TLS endpoints this instance connects
  to, and with ``zenoh_mtls`` the certificates of the peers that connect (a peer without one
  signed by that CA cannot open a link).
- ``zenoh_users_file`` (``user:password`` lines): a peer that connects must authenticate as
  one of those users (Zenoh's ``usrpwd``); a peer without credentials cannot open a session
  with this instance, so it receives nothing and can send nothing.
- With either, access control (``access_control``): every message on the agilegs keys
  (``agilegs/**`` and the ROS 2 namespaces served) in and out is allowed only for those users
  and, with mutual TLS, for peers on a TLS link (whose certificate the CA verified); anything
  else from or to a peer is denied.
- ``zenoh_user`` / ``zenoh_password``: what this instance presents when it connects to a
  router or another instance that authenticates its peers.

:func:`make_dev_certs` writes a development CA and a server and a client certificate
(``agilegs serve --zenoh-dev-certs DIR``).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agilegs.client.zenoh_rpc import credentials
from agilegs.schemas import keys

from .settings import Settings

__all__ = ["ACL_MESSAGES", "DevCerts", "acl_config", "agilegs_keys", "make_dev_certs",
           "read_users", "zenoh_settings"]

log = logging.getLogger(__name__)

ACL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
"""Every message kind Zenoh's access control filters."""


def read_users(path: Path) -> list[str]:
    """The usernames of a ``user:password`` file (ValueError naming a malformed line)."""
    users = []
    for i, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise ValueError(f"{path}:{i}: expected user:password")
        users.append(user)
    if not users:
        raise ValueError(f"{path}: no user:password line")
    return users


def acl_config(key_exprs: list[str], usernames: list[str], tls_peers: bool) -> dict[str, Any]:
    """Access control allowing every message on ``key_exprs`` to the peers authenticated as
    ``usernames`` and (``tls_peers``) to the peers on a TLS link; all else denied."""
    subjects: list[dict[str, Any]] = []
    if usernames:
        subjects.append({"id": "agilegs-users", "usernames": usernames})
    if tls_peers:
        subjects.append({"id": "agilegs-mtls", "link_protocols": ["tls"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [{"id": "agilegs-keys", "messages": ACL_MESSAGES,
                   "flows": ["ingress", "egress"], "permission": "allow",
                   "key_exprs": key_exprs}],
        "subjects": subjects,
        "policies": [{"rules": ["agilegs-keys"], "subjects": [s["id"] for s in subjects]}],
    }


def agilegs_keys(ros2: list[str]) -> list[str]:
    """The key expressions of every agilegs key: ``agilegs/**``, the verbatim ``@service``
    and ``@instances`` chunks (which ``**`` does not match) and the ROS 2 namespaces."""
    return ([f"{keys.PREFIX}/**", f"{keys.PREFIX}/{keys.SERVICE}/**",
             f"{keys.PREFIX}/{keys.INSTANCES}/**"] + [f"{ns.strip('/')}/**" for ns in ros2])


def zenoh_settings(settings: Settings) -> dict[str, Any]:
    """The Zenoh config entries of the server's security settings (see the module
    docstring); empty when none is set."""
    s = settings
    if s.zenoh_dev_certs is not None:
        make_dev_certs(Path(s.zenoh_dev_certs))
    password = s.zenoh_password.get_secret_value() if s.zenoh_password is not None else None
    out = credentials(user=s.zenoh_user, password=password, root_ca=s.zenoh_tls_root_ca,
                      certificate=s.zenoh_tls_certificate if s.zenoh_mtls else None,
                      private_key=s.zenoh_tls_private_key if s.zenoh_mtls else None)
    if s.zenoh_tls_certificate is not None:
        out["transport/link/tls/listen_certificate"] = str(s.zenoh_tls_certificate)
        out["transport/link/tls/listen_private_key"] = str(s.zenoh_tls_private_key)
    if s.zenoh_mtls:
        out["transport/link/tls/enable_mtls"] = True
    users = read_users(Path(s.zenoh_users_file)) if s.zenoh_users_file is not None else []
    if s.zenoh_users_file is not None:
        out["transport/auth/usrpwd/dictionary_file"] = str(s.zenoh_users_file)
    if users or s.zenoh_mtls:
        key_exprs = agilegs_keys(s.ros2)
        # this instance's own user may reach the others of its cluster
        names = users + ([s.zenoh_user] if s.zenoh_user and s.zenoh_user not in users else [])
        out["access_control"] = acl_config(key_exprs, names, s.zenoh_mtls)
    return out


@dataclass(frozen=True)
class DevCerts:
    """The files :func:`make_dev_certs` writes (PEM)."""

    ca: Path
    server_certificate: Path
    server_key: Path
    client_certificate: Path
    client_key: Path


def make_dev_certs(folder: Path, hosts: tuple[str, ...] = ("localhost", "127.0.0.1", "::1"),
                   days: int = 365) -> DevCerts:
    """A development CA (``ca.pem``), a server certificate for ``hosts`` (``server.pem``,
    ``server.key``) and a client certificate (``client.pem``, ``client.key``, common name
    ``agilegs-client``) in ``folder``, made once: existing files are kept. For a development
    network only: the CA's key is not kept, so nothing else can be signed with it."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    folder = Path(folder)
    out = DevCerts(folder / "ca.pem", folder / "server.pem", folder / "server.key",
                   folder / "client.pem", folder / "client.key")
    if all(p.exists() for p in (out.ca, out.server_certificate, out.server_key,
                                out.client_certificate, out.client_key)):
        return out
    folder.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.UTC)

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (x509.CertificateBuilder().subject_name(name("agilegs development CA"))
          .issuer_name(name("agilegs development CA")).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number())
          .not_valid_before(now - dt.timedelta(minutes=5))
          .not_valid_after(now + dt.timedelta(days=days))
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True,
                                       crl_sign=True, content_commitment=False,
                                       key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False,
                                       decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))

    def leaf(cn: str, usage: Any, sans: list[x509.GeneralName]) -> tuple[bytes, bytes]:
        key = ec.generate_private_key(ec.SECP256R1())
        b = (x509.CertificateBuilder().subject_name(name(cn)).issuer_name(ca.subject)
             .public_key(key.public_key()).serial_number(x509.random_serial_number())
             .not_valid_before(now - dt.timedelta(minutes=5))
             .not_valid_after(now + dt.timedelta(days=days))
             .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
             .add_extension(x509.ExtendedKeyUsage([usage]), critical=False))
        if sans:
            b = b.add_extension(x509.SubjectAlternativeName(sans), critical=False)
        cert = b.sign(ca_key, hashes.SHA256())
        return (cert.public_bytes(serialization.Encoding.PEM),
                key.private_bytes(serialization.Encoding.PEM,
                                  serialization.PrivateFormat.PKCS8,
                                  serialization.NoEncryption()))

    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    server_pem, server_key = leaf("agilegs-server", ExtendedKeyUsageOID.SERVER_AUTH, sans)
    client_pem, client_key = leaf("agilegs-client", ExtendedKeyUsageOID.CLIENT_AUTH, [])
    for path, data in ((out.ca, ca.public_bytes(serialization.Encoding.PEM)),
                       (out.server_certificate, server_pem), (out.client_certificate, client_pem),
                       (out.server_key, server_key), (out.client_key, client_key)):
        path.write_bytes(data)
        if path.suffix == ".key":
            path.chmod(0o600)
    log.info("development certificates written to %s", folder)
    return out
