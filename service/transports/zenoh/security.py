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
- Secure by default: a server with a bearer token (``AGILEGS_TOKEN``) and neither a users
  file nor mutual TLS makes its own credentials on first start (:func:`own_credentials`):
  ``<state_dir>/zenoh/users.txt`` (one user, ``agilegs``, with a random password, kept across
  restarts) serves as its users file, so a peer without them cannot open a session; and
  ``<state_dir>/zenoh/client.json`` holds what a client needs (the endpoints, user,
  password: ``ZenohClient(credentials=PATH)``). ``zenoh_insecure`` turns this off.

:func:`make_dev_certs` writes a development CA and a server and a client certificate
(``agilegs serve --zenoh-dev-certs DIR``).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import logging
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agilegs.client.zenoh_rpc import credentials
from agilegs.schemas import keys

from ...settings import Settings

__all__ = ["ACL_MESSAGES", "OWN_USER", "DevCerts", "OwnCredentials", "acl_config",
           "agilegs_keys", "make_dev_certs", "needs_own_credentials", "own_credentials",
           "read_users", "zenoh_settings"]

log = logging.getLogger(__name__)

ACL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
"""Every message kind Zenoh's access control filters."""


class UsersFileError(ValueError):
    """The Zenoh users file cannot be read or holds no ``user:password`` line; the message
    says which and what to do, in one line."""


_MAKE_USERS = ("create it with one user:password line per peer, e.g. printf 'robot:%s\\n' "
               "\"$(openssl rand -hex 16)\" > FILE")


def read_users(path: Path) -> list[str]:
    """The usernames of a ``user:password`` file (:class:`UsersFileError` naming a missing
    file or a malformed line)."""
    users = []
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise UsersFileError(
            f"cannot read the Zenoh users file {path} (--zenoh-users-file, "
            f"AGILEGS_ZENOH_USERS_FILE): {exc.strerror or exc}; "
            + _MAKE_USERS.replace("FILE", str(path))) from None
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise UsersFileError(f"{path}:{i}: expected user:password")
        users.append(user)
    if not users:
        raise UsersFileError(f"{path}: no user:password line; "
                             + _MAKE_USERS.replace("FILE", str(path)))
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
    """The key expressions of every agilegs key: ``agilegs/**``, the verbatim ``@service``,
    ``@instances``, ``@leases`` and ``@members`` chunks (which ``**`` does not match; the
    last two: a fleet's liveliness tokens) and the ROS 2 namespaces."""
    return ([f"{keys.PREFIX}/**", f"{keys.PREFIX}/{keys.SERVICE}/**",
             f"{keys.PREFIX}/{keys.INSTANCES}/**", f"{keys.PREFIX}/{keys.LEASES}/**",
             f"{keys.PREFIX}/{keys.MEMBERS}/**"] + [f"{ns.strip('/')}/**" for ns in ros2])


OWN_USER = "agilegs"
"""The Zenoh user a server makes for itself (:func:`own_credentials`)."""


@dataclass(frozen=True)
class OwnCredentials:
    """The files :func:`own_credentials` keeps, and the password it made."""

    users_file: Path
    client_file: Path
    user: str
    password: str


def needs_own_credentials(settings: Settings) -> bool:
    """Whether the server makes its own Zenoh credentials: Zenoh on, a bearer token set, no
    users file, no mutual TLS, and not ``zenoh_insecure``."""
    s = settings
    return (s.zenoh and s.token is not None and not s.zenoh_insecure
            and s.zenoh_users_file is None and not s.zenoh_mtls)


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by its owner only (atomically)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def own_credentials(folder: Path, connect: list[str], root_ca: Path | None = None
                    ) -> OwnCredentials:
    """The server's own Zenoh credentials in ``folder``: ``users.txt`` (``agilegs:<random
    password>``, made once and kept) and ``client.json`` (rewritten: ``connect``, the user,
    the password and ``root_ca``, what :func:`agilegs.client.zenoh_rpc.read_credentials`
    reads), both readable by their owner only."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(0o700)
    users_file = folder / "users.txt"
    password = None
    if users_file.exists():
        for line in users_file.read_text().splitlines():
            user, sep, pw = line.strip().partition(":")
            if sep and user == OWN_USER and pw:
                password = pw
                break
    if password is None:
        password = secrets.token_urlsafe(32)
        _write_private(users_file, f"{OWN_USER}:{password}\n")
        log.info("zenoh: made the credentials of user %r in %s", OWN_USER, users_file)
    client: dict[str, Any] = {"connect": list(connect), "user": OWN_USER, "password": password}
    if root_ca is not None:
        client["tls_root_ca"] = str(Path(root_ca).resolve())
    client_file = folder / "client.json"
    _write_private(client_file, json.dumps(client, indent=2) + "\n")
    return OwnCredentials(users_file, client_file, OWN_USER, password)


def zenoh_settings(settings: Settings) -> dict[str, Any]:
    """The Zenoh config entries of the server's security settings (see the module
    docstring); empty when none is set."""
    s = settings
    if s.zenoh_dev_certs is not None:
        make_dev_certs(Path(s.zenoh_dev_certs))
    password = s.zenoh_password.get_secret_value() if s.zenoh_password is not None else None
    user = s.zenoh_user
    users_file = s.zenoh_users_file
    if needs_own_credentials(s):
        own = own_credentials(Path(s.state_dir) / "zenoh", s.zenoh_listen, s.zenoh_tls_root_ca)
        users_file = own.users_file
        if user is None:  # presented when it connects to a router or the robot's bridge
            user, password = own.user, own.password
        log.info("zenoh: peers must authenticate; a client connects with "
                 "ZenohClient(credentials=%r, token=...) (the endpoints, user and password "
                 "in that file)", str(own.client_file))
    out = credentials(user=user, password=password, root_ca=s.zenoh_tls_root_ca,
                      certificate=s.zenoh_tls_certificate if s.zenoh_mtls else None,
                      private_key=s.zenoh_tls_private_key if s.zenoh_mtls else None)
    if s.zenoh_tls_certificate is not None:
        out["transport/link/tls/listen_certificate"] = str(s.zenoh_tls_certificate)
        out["transport/link/tls/listen_private_key"] = str(s.zenoh_tls_private_key)
    if s.zenoh_mtls:
        out["transport/link/tls/enable_mtls"] = True
    users = read_users(Path(users_file)) if users_file is not None else []
    if users_file is not None:
        out["transport/auth/usrpwd/dictionary_file"] = str(users_file)
    if users or s.zenoh_mtls:
        key_exprs = agilegs_keys(s.ros2)
        # this instance's own user may reach the others of its cluster
        names = users + ([user] if user and user not in users else [])
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
