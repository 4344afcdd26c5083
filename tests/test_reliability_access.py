"""Issue 7, item 5: access.  Loopback by default; CURVE with `lacuna keys` key files and an allow
list; the daemon refuses to start exposed without keys; OSC limited to allowed source addresses;
no pickle anywhere in the source tree.  Real daemon process, real sockets, real key files.
"""
from __future__ import annotations

import ast
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import fuzzgen
import numpy as np
import pytest
import zmq
from reliability_daemon import Daemon, Sockets, control, free_port, recv_msg, status, write_config

from daemon import security, wire

NO_ANSWER_MS = 1500  # "gets nothing": a CURVE handshake on loopback takes ~1 ms
ROOT = Path(__file__).resolve().parents[1]
CH = ["lfemur.rx", "lfemur.ry", "ltibia.rx"]


def lacuna(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lacuna.cli", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def keys(tmp_path):
    """Server pair, two clients (one authorized, one not) made with the real `lacuna keys` command."""
    kd = tmp_path / "keys"
    for name in ("server", "studio", "stranger"):
        r = lacuna("keys", str(kd), "--name", name)
        assert r.returncode == 0, r.stderr
    auth = tmp_path / "authorized"
    auth.mkdir()
    shutil.copy(kd / "studio.key", auth / "studio.key")
    return kd, auth


def curve_config(tmp_path, kd, auth, **kw):
    extra = (f'[security]\nserver_secret_key = "{kd / "server.key_secret"}"\nauthorized_keys = "{auth}"\n')
    return write_config(tmp_path / "lacuna.toml", {"floor": {"builtin": "passthrough"}}, extra=extra, **kw)


def curve_dealer(S: Sockets, endpoint: str, kd: Path, name: str) -> zmq.Socket:
    s = S.make(zmq.DEALER)
    security.configure_client(s, str(kd / f"{name}.key_secret"), str(kd / "server.key"))
    s.connect(endpoint)
    return s


def frame(sid: str, seq: int) -> bytes:
    return wire.encode(wire.Frame(sid, seq, seq / 120.0, np.array([1.0, np.nan, 3.0], np.float32)))


# ---- lacuna keys -----------------------------------------------------------------------------------
def test_lacuna_keys_writes_a_0600_secret_and_refuses_to_overwrite(tmp_path):
    r = lacuna("keys", str(tmp_path / "k"), "--name", "cam1")
    assert r.returncode == 0, r.stderr
    sec = tmp_path / "k" / "cam1.key_secret"
    assert os.stat(sec).st_mode & 0o777 == 0o600
    pub, secret = zmq.auth.load_certificate(str(sec))
    assert len(pub) == 40 and len(secret) == 40  # Z85 of 32-byte curve25519 keys
    assert zmq.auth.load_certificate(str(tmp_path / "k" / "cam1.key"))[1] is None  # public file: no secret
    again = lacuna("keys", str(tmp_path / "k"), "--name", "cam1")
    assert again.returncode == 2 and "refusing to overwrite" in again.stderr
    assert zmq.auth.load_certificate(str(sec)) == (pub, secret)
    forced = lacuna("keys", str(tmp_path / "k"), "--name", "cam1", "--force")
    assert forced.returncode == 0 and zmq.auth.load_certificate(str(sec))[0] != pub
    assert os.stat(sec).st_mode & 0o777 == 0o600
    bad = lacuna("keys", str(tmp_path / "k"), "--name", "../escape")
    assert bad.returncode == 2 and "--name" in bad.stderr


def test_lacuna_keys_never_writes_through_a_symlink(tmp_path):
    """Issue 18 F13: a (dangling) symlink at the secret key's path was followed and the key
    written to its target.  Now refused, the target never created; with --force the link
    itself is replaced by a fresh 0600 file."""
    kd = tmp_path / "k"
    kd.mkdir()
    target = tmp_path / "elsewhere" / "stolen"
    (tmp_path / "elsewhere").mkdir()
    (kd / "cam2.key_secret").symlink_to(target)  # dangling
    r = lacuna("keys", str(kd), "--name", "cam2")
    assert r.returncode == 2 and "symlink" in r.stderr and "refusing" in r.stderr, r.stderr
    assert not target.exists() and not (kd / "cam2.key").exists()
    forced = lacuna("keys", str(kd), "--name", "cam2", "--force")
    assert forced.returncode == 0, forced.stderr
    sec = kd / "cam2.key_secret"
    assert not sec.is_symlink() and not target.exists() and os.stat(sec).st_mode & 0o777 == 0o600
    assert zmq.auth.load_certificate(str(sec))[1] is not None


# ---- CURVE --------------------------------------------------------------------------------------------
def test_curve_client_without_the_key_gets_nothing_and_a_listed_key_gets_served(tmp_path, keys):
    kd, auth = keys
    ep = curve_config(tmp_path, kd, auth)
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        plain = S.make(zmq.DEALER, ep["router"])  # no CURVE at all
        plain.send(frame("plain", 0))
        stranger = curve_dealer(S, ep["router"], kd, "stranger")  # CURVE, but not on the allow list
        stranger.send(frame("stranger", 0))
        studio = curve_dealer(S, ep["router"], kd, "studio")
        studio.send(frame("studio", 0))
        m = recv_msg(studio)
        assert isinstance(m, wire.FillMsg) and m.stream == "studio" and m.angles[0] == 1.0
        assert not plain.poll(NO_ANSWER_MS) and not stranger.poll(NO_ANSWER_MS)
        # the PUB output is CURVE too: an unauthenticated subscriber sees nothing
        sub_plain = S.make(zmq.SUB, ep["pub"])
        sub_plain.setsockopt(zmq.SUBSCRIBE, b"")
        sub_ok = S.make(zmq.SUB)
        security.configure_client(sub_ok, str(kd / "studio.key_secret"), str(kd / "server.key"))
        sub_ok.setsockopt(zmq.SUBSCRIBE, b"")
        sub_ok.connect(ep["pub"])
        for seq in range(1, 40):  # PUB drops until a subscription arrives: keep sending
            studio.send(frame("studio", seq))
            assert isinstance(recv_msg(studio), wire.FillMsg)
            if sub_ok.poll(50):
                break
        topic, body = sub_ok.recv_multipart()
        assert topic == b"studio" and isinstance(wire.decode(body), wire.FillMsg)
        assert not sub_plain.poll(NO_ANSWER_MS // 3)
        st = control(studio, "status")
        assert st["security"]["curve"] is True and st["security"]["auth_denied"] >= 1
        assert st["security"]["authorized_keys"] == 1
        assert set(st["streams"]) == {"studio"}  # nothing from the others reached a session
        assert d.alive()
    finally:
        S.close()
        d.stop()


def test_sighup_rereads_the_authorized_keys(tmp_path, keys):
    kd, auth = keys
    ep = curve_config(tmp_path, kd, auth)
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        stranger = curve_dealer(S, ep["router"], kd, "stranger")
        stranger.send(frame("late-comer", 0))
        assert not stranger.poll(NO_ANSWER_MS)
        shutil.copy(kd / "stranger.key", auth / "stranger.key")
        d.signal(signal.SIGHUP)
        d.wait_for("reload_done", 10)
        # a refused handshake ends that connection for good (libzmq does not retry after a
        # ZAP refusal), so the client connects again, as a client library does after a timeout
        stranger = curve_dealer(S, ep["router"], kd, "stranger")
        stranger.send(frame("late-comer", 0))
        m = recv_msg(stranger)
        assert isinstance(m, wire.FillMsg) and m.stream == "late-comer"
        assert control(stranger, "status")["security"]["authorized_keys"] == 2
        # `lacuna status` against a CURVE daemon: with a listed key it answers, without one it times out
        r = lacuna("status", "--connect", ep["router"], "--json", "--key", str(kd / "stranger.key_secret"),
                   "--server-key", str(kd / "server.key"))
        assert r.returncode == 0 and '"late-comer"' in r.stdout, r.stderr
        r = lacuna("status", "--connect", ep["router"], "--timeout", "1")
        assert r.returncode == 2 and "no answer" in r.stderr
    finally:
        S.close()
        d.stop()


# ---- the exposure rule ----------------------------------------------------------------------------------
def test_daemon_refuses_to_bind_a_non_loopback_address_without_keys(tmp_path):
    port = free_port()
    cfg = tmp_path / "open.toml"
    cfg.write_text(f'[models.floor]\nbuiltin = "passthrough"\n[zmq]\nrouter = "tcp://0.0.0.0:{port}"\n')
    r = lacuna("serve", "--config", str(cfg))
    assert r.returncode == 2
    assert "not a loopback address" in r.stderr and "CURVE" in r.stderr and "lacuna keys" in r.stderr
    with socket.socket() as s:  # and it never bound the port
        s.bind(("0.0.0.0", port))
    assert lacuna("serve", "--config", str(cfg), "--check").returncode == 2
    osc_open = tmp_path / "osc.toml"
    osc_open.write_text(f'[models.floor]\nbuiltin = "passthrough"\n[osc]\nlisten = "0.0.0.0:{port}"\n')
    r = lacuna("serve", "--config", str(osc_open))
    assert r.returncode == 2 and "osc_allow" in r.stderr


def _scrape(port: int, source: str) -> bytes:
    with socket.socket() as s:
        s.settimeout(10)
        s.bind((source, 0))
        s.connect(("127.0.0.1", port))
        buf = b""
        try:
            s.sendall(b"GET /metrics HTTP/1.0\r\n\r\n")
            while (b := s.recv(65536)):
                buf += b
        except ConnectionResetError:  # (closed with the request unread: a reset)
            pass
        return buf


def test_metrics_endpoint_off_loopback_needs_an_allow_list(tmp_path):
    """Issue 18 F8: metrics.http on 0.0.0.0 started with no keys and no allow list, exposing
    stream and model names.  Now refused (exit 2, port never bound) unless metrics.allow lists
    the scrapers; then others are closed unanswered and counted."""
    port = free_port()
    cfg = tmp_path / "m.toml"
    base = f'[models.floor]\nbuiltin = "passthrough"\n[zmq]\nrouter = "tcp://127.0.0.1:{free_port()}"\n'
    cfg.write_text(base + f'[metrics]\nhttp = "0.0.0.0:{port}"\n')
    r = lacuna("serve", "--config", str(cfg))
    assert r.returncode == 2 and "metrics.allow" in r.stderr and "not a loopback address" in r.stderr, r.stderr
    with socket.socket() as s:  # it never bound the port
        s.bind(("0.0.0.0", port))
    ep = write_config(tmp_path / "ok.toml", {"floor": {"builtin": "passthrough"}},
                      extra=f'[metrics]\nhttp = "0.0.0.0:{port}"\nallow = ["127.0.0.2"]\n')
    d = Daemon(tmp_path / "ok.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        assert b"lacuna_up 1" in _scrape(port, "127.0.0.2")
        assert _scrape(port, "127.0.0.1") == b""  # not on the list: closed, nothing said
        st = status(S, ep["router"])
        assert st["metrics_http"]["denied"] == 1 and st["metrics_http"]["served"] == 1
    finally:
        S.close()
        d.stop()


def test_exposed_bind_with_keys_serves_only_listed_clients(tmp_path, keys):
    kd, auth = keys
    port = free_port(host="0.0.0.0")
    curve_config(tmp_path, kd, auth, router=f"tcp://0.0.0.0:{port}")
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        plain = S.make(zmq.DEALER, f"tcp://127.0.0.1:{port}")
        plain.send(frame("plain", 0))
        studio = curve_dealer(S, f"tcp://127.0.0.1:{port}", kd, "studio")
        studio.send(frame("studio", 0))
        assert isinstance(recv_msg(studio), wire.FillMsg)
        assert not plain.poll(NO_ANSWER_MS)
    finally:
        S.close()
        d.stop()


def test_secret_key_readable_by_others_is_refused(tmp_path, keys):
    kd, auth = keys
    os.chmod(kd / "server.key_secret", 0o644)
    curve_config(tmp_path, kd, auth)
    r = lacuna("serve", "--config", str(tmp_path / "lacuna.toml"))
    assert r.returncode == 2 and "chmod 600" in r.stderr
    os.chmod(kd / "server.key_secret", 0o600)
    for f in auth.iterdir():
        f.unlink()
    r = lacuna("serve", "--config", str(tmp_path / "lacuna.toml"))
    assert r.returncode == 2 and "no *.key files" in r.stderr


def test_loopback_rule_on_endpoints():
    local = ["tcp://127.0.0.1:5555", "tcp://127.0.0.2:1", "tcp://[::1]:5555", "tcp://localhost:5555",
             "ipc:///run/lacuna/sock", "inproc://x"]
    exposed = ["tcp://0.0.0.0:5555", "tcp://*:5555", "tcp://eth0:5555", "tcp://192.168.1.5:5555",
               "tcp://[::]:5555", "tcp://studio-host:5555", "epgm://eth0;239.1.1.1:5555", "ws://127.0.0.1:1"]
    assert all(security.endpoint_is_local(e) for e in local)
    assert not any(security.endpoint_is_local(e) for e in exposed)


def test_key_paths_expand_the_systemd_credentials_directory(keys, monkeypatch):
    kd, auth = keys
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(kd))
    spec = security.parse_config({"server_secret_key": "$CREDENTIALS_DIRECTORY/server.key_secret",
                                  "authorized_keys": str(auth)}, "t.toml", "/elsewhere")
    assert spec.server_secret_key == str(kd / "server.key_secret") and spec.curve
    security.check_exposure({"zmq.router": "tcp://0.0.0.0:5555"}, None, spec)  # keys readable: allowed
    with pytest.raises(security.SecurityError, match="authorized_keys go together"):
        security.parse_config({"server_secret_key": "x"})
    with pytest.raises(security.SecurityError, match="not an IP address"):
        security.parse_config({"osc_allow": ["studio-pc"]})


# ---- OSC source allow list -------------------------------------------------------------------------------
def test_osc_from_a_source_not_on_the_allow_list_is_rejected_and_counted(tmp_path):
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"builtin": "passthrough", "channels": CH}}, osc=True,
                      extra='[security]\nosc_allow = ["127.0.0.1"]\n')
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    socks = []
    try:
        allowed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        allowed.bind(("127.0.0.1", 0))
        other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        other.bind(("127.0.0.2", 0))  # another source address on loopback
        socks += [allowed, other]
        for s in socks:
            s.settimeout(NO_ANSWER_MS / 1000)
        n_other = 25
        for seq in range(n_other):
            other.sendto(fuzzgen.osc_frame("intruder", seq, 0.0, [1.0, 2.0, 3.0]), ep["osc"])
        other.sendto(b"garbage from elsewhere", ep["osc"])  # not even decoded: counted the same way
        allowed.sendto(fuzzgen.osc_frame("studio", 0, 0.0, [1.0, float("nan"), 3.0]), ep["osc"])
        data = allowed.recv(65535)
        assert data.startswith(b"#bundle") and b"/lacuna/fill" in data and b"studio" in data
        with pytest.raises(socket.timeout):
            other.recv(65535)  # no answer at all: the daemon is not a reflector
        st = control(S.make(zmq.DEALER, ep["router"]), "status")
        assert st["rejected"].get("source_not_allowed") == n_other + 1
        assert st["security"]["osc_denied"] == n_other + 1
        assert set(st["streams"]) == {"studio"}
    finally:
        for s in socks:
            s.close()
        S.close()
        d.stop()


# ---- the systemd unit -----------------------------------------------------------------------------------
SANDBOX = {"DynamicUser": "yes", "NoNewPrivileges": "yes", "ProtectSystem": "strict", "ProtectHome": "yes",
           "PrivateTmp": "yes", "PrivateDevices": "yes", "CapabilityBoundingSet": "", "AmbientCapabilities": "",
           "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6", "MemoryDenyWriteExecute": "yes", "UMask": "0077"}


def test_systemd_unit_runs_unprivileged_and_sandboxed(tmp_path):
    unit = (ROOT / "systemd" / "lacuna.service").read_text()
    settings: dict[str, list[str]] = {}
    for line in unit.splitlines():
        if "=" in line and not line.lstrip().startswith(("#", ";")):
            k, v = line.split("=", 1)
            settings.setdefault(k.strip(), []).append(v.strip())
    for k, v in SANDBOX.items():
        assert settings.get(k, [None])[-1] == v, f"{k}= should be {v!r} (got {settings.get(k)})"
    assert "User" not in settings and "Group" not in settings  # never a fixed (possibly privileged) account
    exe = shutil.which("systemd-analyze")
    if exe is None:  # the static checks above still ran
        pytest.skip("systemd-analyze is not installed: exposure score not measured")
    shutil.copy(ROOT / "systemd" / "lacuna.service", tmp_path / "lacuna.service")
    r = subprocess.run([exe, "security", "--offline=true", "--threshold=20", str(tmp_path / "lacuna.service")],
                       capture_output=True, text=True, timeout=60)
    score = [ln for ln in r.stdout.splitlines() if "Overall exposure level" in ln]
    assert r.returncode == 0, score or r.stderr  # exposure <= 2.0 of 10 ("OK" is below 3)
    print("\n" + score[0])


# ---- no pickle ----------------------------------------------------------------------------------------------
UNSAFE_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "shelve", "marshal", "joblib"}


def _unsafe_uses(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if a.name.split(".")[0] in UNSAFE_MODULES]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in UNSAFE_MODULES:
            found.append(f"from {node.module} import ...")
        elif isinstance(node, ast.Call):
            for kw in node.keywords:
                if kw.arg == "allow_pickle" and not (isinstance(kw.value, ast.Constant) and kw.value.value is False):
                    found.append(f"allow_pickle={ast.unparse(kw.value)}")
            fn = ast.unparse(node.func)
            if fn.endswith(("torch.load", "yaml.load", "yaml.unsafe_load", "pd.read_pickle", "np.load")):
                # np.load reads pickles only with allow_pickle=True (checked above); the others always can
                if not fn.endswith("np.load"):
                    found.append(fn)
        elif isinstance(node, ast.Attribute) and node.attr in ("loads", "load", "Unpickler") and \
                isinstance(node.value, ast.Name) and node.value.id in UNSAFE_MODULES:
            found.append(f"{node.value.id}.{node.attr}")
    return [f"{path.relative_to(ROOT)}:{x}" for x in found]


def test_no_pickle_anywhere_outside_tests():
    files = [p for p in ROOT.rglob("*.py") if not ({".venv", "tests", ".git", "build"} & set(p.relative_to(ROOT).parts))]
    assert len(files) > 20  # the scan really covers the source tree
    bad = [u for p in files for u in _unsafe_uses(p)]
    assert bad == []
    # and the checker catches what it must catch
    probe = ROOT / "tests" / "_pickle_probe.txt"
    try:
        probe.write_text("import pickle\nnp.load(f, allow_pickle=True)\nx = dill.loads(b)\n")
        assert len(_unsafe_uses(probe)) == 3
    finally:
        probe.unlink()
