"""Zenoh traffic only authenticated peers see (a real ``agilegs serve`` with a users file, TLS
from its development certificates, and the HTTP token): a peer without credentials that
reaches the listen endpoints receives no decision and changes nothing; the SDK's ZenohClient
with the credentials and the CA works as before."""

from __future__ import annotations

import json
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import SMALL_INTRINSICS, gaussian_blob, ring_poses

from agilegs.client import Client, TransportError, ZenohClient
from agilegs.client.zenoh_rpc import (
    credentials,
    first_answer,
    open_session,
    read_credentials,
)
from agilegs.schemas import codec
from agilegs.service.launch import free_port
from agilegs.service.settings import Settings
from agilegs.service.transports.zenoh.security import make_dev_certs, read_users, zenoh_settings

TOKEN = "http-secret"


def test_settings_give_zenoh_its_own_security(tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("robot:secret\nviewer:other\n")
    assert read_users(users) == ["robot", "viewer"]
    (tmp_path / "bad.txt").write_text("nopassword\n")
    with pytest.raises(ValueError, match="bad.txt:1"):
        read_users(tmp_path / "bad.txt")
    assert zenoh_settings(Settings()) == {}
    got = zenoh_settings(Settings(zenoh_users_file=users, zenoh_dev_certs=tmp_path / "certs",
                                  ros2=["/bot1/agilegs"]))
    assert got["transport/auth/usrpwd/dictionary_file"] == str(users)
    assert got["transport/link/tls/listen_certificate"] == str(tmp_path / "certs/server.pem")
    acl = got["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert acl["rules"][0]["key_exprs"] == ["agilegs/**", "agilegs/@service/**",
                                            "agilegs/@instances/**", "agilegs/@leases/**",
                                            "agilegs/@members/**", "bot1/agilegs/**"]
    assert acl["subjects"] == [{"id": "agilegs-users", "usernames": ["robot", "viewer"]}]
    mtls = zenoh_settings(Settings(zenoh_mtls=True, zenoh_dev_certs=tmp_path / "certs"))
    assert mtls["transport/link/tls/enable_mtls"] is True
    assert {"id": "agilegs-mtls", "link_protocols": ["tls"]} in mtls["access_control"][
        "subjects"]
    with pytest.raises(ValueError):
        Settings(zenoh_mtls=True)  # needs a CA and a certificate
    with pytest.raises(ValueError):
        Settings(zenoh_user="robot")  # needs its password


def test_a_token_makes_zenoh_credentials_kept_across_restarts(tmp_path: Path) -> None:
    state = tmp_path / "state"
    s = Settings(state_dir=state, token="t", zenoh_listen=["tcp/127.0.0.1:7999"])
    got = zenoh_settings(s)
    users = state / "zenoh" / "users.txt"
    assert got["transport/auth/usrpwd/dictionary_file"] == str(users)
    assert read_users(users) == ["agilegs"]
    assert got["access_control"]["default_permission"] == "deny"
    assert got["access_control"]["subjects"] == [{"id": "agilegs-users",
                                                  "usernames": ["agilegs"]}]
    saved = read_credentials(state / "zenoh" / "client.json")
    assert saved["connect"] == ["tcp/127.0.0.1:7999"] and saved["user"] == "agilegs"
    assert got["transport/auth/usrpwd/password"] == saved["password"]  # presented to a router
    for f in ("users.txt", "client.json"):
        assert (state / "zenoh" / f).stat().st_mode & 0o077 == 0  # the owner's only
    again = zenoh_settings(s)  # a restart keeps the password
    assert read_credentials(state / "zenoh" / "client.json")["password"] == saved["password"]
    assert again["access_control"] == got["access_control"]
    # no token (development mode), or the explicit insecure flag: no credentials made
    assert zenoh_settings(Settings(state_dir=tmp_path / "dev")) == {}
    assert zenoh_settings(Settings(state_dir=tmp_path / "open", token="t",
                                   zenoh_insecure=True)) == {}
    assert not (tmp_path / "dev" / "zenoh").exists() and not (tmp_path / "open").exists()


def test_a_server_started_as_the_readme_says_shows_a_stranger_nothing(
        server_factory: Any) -> None:
    """``AGILEGS_TOKEN=... agilegs serve``, nothing else: a peer without credentials that
    subscribes to ``agilegs/**`` during selects over HTTP and over Zenoh receives nothing;
    the client with the server's credentials file receives both decisions."""
    srv = server_factory(env={"AGILEGS_TOKEN": TOKEN}).start()
    creds = srv.zenoh_credentials
    assert creds is not None
    assert "peers must authenticate" in srv.log()
    sid = f"dflt-{uuid.uuid4().hex[:6]}"
    with Client(srv.url, token=TOKEN, timeout=60) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=gaussian_blob(100),
                         pool=ring_poses(8))
    stranger_saw: list[str] = []
    robot_saw: list[str] = []
    stranger = open_session([], [srv.zenoh_endpoint], "peer")
    sub = stranger.declare_subscriber("agilegs/**",
                                      lambda sample: stranger_saw.append(str(sample.key_expr)))
    try:
        with ZenohClient(token=TOKEN, credentials=creds, timeout=30) as zc:
            zc.subscribe_decisions(sid, lambda d: robot_saw.append(d.session))
            time.sleep(0.5)
            zc.select(sid, method="random")  # over Zenoh
            with Client(srv.url, token=TOKEN, timeout=60) as c:
                c.select(sid, method="random")  # over HTTP
            deadline = time.monotonic() + 5
            while len(robot_saw) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
        assert robot_saw == [sid, sid]
        assert stranger_saw == []
        ans, _ = first_answer(stranger, f"agilegs/{sid}/get_session", timeout=1.0,
                              attachment=f"Bearer {TOKEN}".encode())
        assert ans is None  # the token alone does not open Zenoh
    finally:
        sub.undeclare()
        stranger.close()


def test_without_a_token_the_server_says_it_is_open(server_factory: Any) -> None:
    srv = server_factory().start()
    assert srv.zenoh_credentials is None
    assert "development mode: no AGILEGS_TOKEN" in srv.log()
    with ZenohClient([srv.zenoh_endpoint], timeout=30) as zc:
        assert zc.list_sessions().sessions == []


def test_an_unauthenticated_peer_sees_nothing_and_changes_nothing(server_factory: Any,
                                                                  tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("robot:secret\n")
    certs = make_dev_certs(tmp_path / "certs")
    tls = f"tls/127.0.0.1:{free_port()}"
    srv = server_factory(env={"AGILEGS_TOKEN": TOKEN, "AGILEGS_ZENOH_USERS_FILE": str(users),
                              "AGILEGS_ZENOH_DEV_CERTS": str(tmp_path / "certs")},
                         args=["--zenoh-listen", tls]).start()
    sid = f"sec-{uuid.uuid4().hex[:6]}"
    with Client(srv.url, token=TOKEN, timeout=60) as c:
        c.create_session(SMALL_INTRINSICS, id=sid, gaussians=gaussian_blob(100),
                         pool=ring_poses(8))
    seen: dict[str, list[str]] = {"tcp": [], "tls": [], "robot": []}
    lock = threading.Lock()

    def listener(name: str) -> Any:
        def on_sample(sample: Any) -> None:
            with lock:
                seen[name].append(str(sample.key_expr))
        return on_sample

    # peers with no credentials, on either endpoint (TLS: they trust the CA, so only the
    # missing credentials keep them out)
    anon_tcp = open_session([], [srv.zenoh_endpoint], "peer")
    anon_tls = open_session([], [tls], "peer", credentials(root_ca=certs.ca))
    intruder = open_session([], [tls], "peer", credentials(root_ca=certs.ca))
    subs = [anon_tcp.declare_subscriber("agilegs/**", listener("tcp")),
            anon_tls.declare_subscriber("agilegs/**", listener("tls"))]
    try:
        with ZenohClient([tls], token=TOKEN, user="robot", password="secret",
                         tls_root_ca=certs.ca, timeout=30) as zc:
            zc.subscribe_decisions(sid, lambda d: seen["robot"].append(d.session))
            time.sleep(0.5)
            decision = zc.select(sid, method="random")  # over authenticated Zenoh
            with Client(srv.url, token=TOKEN, timeout=60) as c:
                c.select(sid, method="random")  # over authenticated HTTP
                before = c.get_session(sid)
            # the anonymous peers try to change the session and to query it
            intruder.put(f"agilegs/{sid}/candidates",
                         codec.dump({"poses": [p.tolist() for p in ring_poses(3)]},
                                    codec.MSGPACK), attachment=f"Bearer {TOKEN}".encode())
            ans, _ = first_answer(intruder, f"agilegs/{sid}/get_session", timeout=1.0,
                                  attachment=f"Bearer {TOKEN}".encode())
            assert ans is None
            deadline = time.monotonic() + 5
            while len(seen["robot"]) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
            assert decision.session == sid
        with Client(srv.url, token=TOKEN, timeout=60) as c:
            after = c.get_session(sid)
        assert (after.version, after.pool_size) == (before.version, before.pool_size) == (
            before.version, 8)
        assert len(seen["robot"]) >= 2  # both decisions reached the authenticated peer
        assert seen["tcp"] == [] and seen["tls"] == []  # and none the others
        # no credentials, or wrong ones: the SDK client cannot reach the server at all
        for kw in ({}, {"user": "robot", "password": "wrong"}):
            t0 = time.monotonic()
            with pytest.raises(TransportError, match="credentials") as exc:
                ZenohClient([tls], token=TOKEN, tls_root_ca=certs.ca, timeout=2.0, **kw)
            assert time.monotonic() - t0 < 4.0  # within the timeout, not the 10 s of wait
            assert "refused this client's link" in str(exc.value)
        assert httpx.get(f"{srv.url}/healthz", headers={
            "authorization": f"Bearer {TOKEN}"}).status_code == 200
    finally:
        for s in subs:
            s.undeclare()
        for z in (anon_tcp, anon_tls, intruder):
            z.close()



def test_the_routers_secure_block_loads_with_zenoh() -> None:
    import zenoh

    from agilegs.service.transports.zenoh.security import ACL_MESSAGES, agilegs_keys

    text = (Path(__file__).resolve().parents[2] / "deploy" / "zenoh-router.json5").read_text()
    block = text.split("// >>> secure\n", 1)[1].split("  // <<< secure", 1)[0]
    lines = [line.replace("// ", "", 1) for line in block.splitlines()]
    conf = zenoh.Config.from_json5("{" + "\n".join(lines) + "}")
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert acl["rules"][0]["messages"] == ACL_MESSAGES
    assert acl["rules"][0]["key_exprs"] == agilegs_keys([])
    assert json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file"))
