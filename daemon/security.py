"""Who may talk to the daemon: ZeroMQ CURVE with an allow list of client keys, and an OSC
source-address allow list.

The rule
--------
* Loopback by default: every endpoint in the default config is ``127.0.0.1``.
* A ZeroMQ socket *bound* to anything but loopback (``tcp://0.0.0.0:5555``, ``tcp://*:5555``,
  an interface name, a LAN address, a host name) needs CURVE: the ``[security]`` section must
  name the daemon's secret key file and a directory of authorized client public keys, or the
  daemon refuses to start (:func:`check_exposure`, called by config validation).  Once keys are
  configured, *every* bound ZeroMQ socket (router, pull, pub) is a CURVE server, loopback or not:
  a studio that set up keys expects them to be asked for everywhere.
* OSC has no authentication, so OSC listening on a non-loopback address needs ``osc_allow``, a
  list of source addresses/networks; datagrams from other sources are counted and dropped without
  an answer (answering would make the daemon a reflector).

Config (paths relative to the config file; ``$VARS`` expanded, e.g. ``$CREDENTIALS_DIRECTORY``)::

    [security]
    server_secret_key = "keys/server.key_secret"  # lacuna keys keys --name server
    authorized_keys = "keys/authorized"             # *.key public files of allowed clients
    osc_allow = ["127.0.0.1", "192.168.10.0/24"]    # OSC senders allowed in
    sub_server_key = "keys/capture.key"             # optional: CURVE public key of the PUB that
                                                    # zmq.sub connects to (the daemon is its client)

Key files are ZeroMQ's own certificate format (``zmq.auth.create_certificates``), made by
``lacuna keys`` (daemon/keys_cli.py).  A secret key file readable by group or others is refused,
as ssh refuses such private keys.  SIGHUP re-reads the authorized keys directory.
"""
from __future__ import annotations

import glob
import ipaddress
import os
import stat
import threading
from dataclasses import dataclass, field
from typing import Any

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from daemon.errors import ConfigError
from daemon.safeopen import check_regular, kind_of

ZAP_DOMAIN = "lacuna"
LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost")
SECURITY_KEYS = ("server_secret_key", "authorized_keys", "osc_allow", "sub_server_key", "operator_keys")


class SecurityError(ConfigError):
    """Keys missing, unreadable or too open; a non-loopback bind without authentication.  A
    ConfigError, so a reload that meets one keeps the old config like any other bad config."""


# ---- configuration ----------------------------------------------------------------------------
@dataclass
class SecuritySpec:
    """The ``[security]`` section, paths resolved.  All optional; an empty spec = loopback only."""

    server_secret_key: str | None = None
    authorized_keys: str | None = None
    osc_allow: list[str] | None = None  # as written, for status
    sub_server_key: str | None = None
    operator_keys: str | None = None  # directory of *.key: the clients that may reload and reset others' streams
    osc_networks: list[ipaddress.IPv4Network | ipaddress.IPv6Network] | None = field(default=None, repr=False)

    @property
    def curve(self) -> bool:
        return self.server_secret_key is not None


def parse_config(raw: Any, where: str = "<config>", base: str | None = None) -> SecuritySpec:
    """Validate the ``[security]`` table (``None`` when absent).  Raises SecurityError naming the key."""
    if raw is None:
        return SecuritySpec()
    if not isinstance(raw, dict):
        raise SecurityError(f"{where}: [security] must be a table (got {type(raw).__name__})")
    for k in raw:
        if k not in SECURITY_KEYS:
            raise SecurityError(f"{where}: unknown key security.{k} (known: {', '.join(SECURITY_KEYS)})")
    base = base or os.getcwd()
    spec = SecuritySpec()
    for k in ("server_secret_key", "authorized_keys", "sub_server_key", "operator_keys"):
        if k in raw:
            v = raw[k]
            if not isinstance(v, str) or not v:
                raise SecurityError(f"{where}: security.{k} must be a file path string (got {v!r:.60})")
            # $CREDENTIALS_DIRECTORY: under systemd, LoadCredential= hands the secret key to the
            # DynamicUser service as a 0400 file it owns (see docs/RELIABILITY.md)
            v = os.path.expandvars(v)
            setattr(spec, k, v if os.path.isabs(v) else os.path.join(base, v))
    if (spec.server_secret_key is None) != (spec.authorized_keys is None):
        raise SecurityError(f"{where}: security.server_secret_key and security.authorized_keys go together "
                            f"(CURVE needs the daemon's key pair and the list of client keys it lets in)")
    if spec.operator_keys is not None and spec.server_secret_key is None:
        raise SecurityError(f"{where}: security.operator_keys needs CURVE (security.server_secret_key and "
                            f"authorized_keys); without it every local ROUTER peer is an operator")
    if "osc_allow" in raw:
        v = raw["osc_allow"]
        if not isinstance(v, list) or not all(isinstance(a, str) for a in v):
            raise SecurityError(f"{where}: security.osc_allow must be a list of addresses or networks (got {v!r:.60})")
        spec.osc_allow = list(v)
        spec.osc_networks = [_network(where, a) for a in v]
    return spec


def _network(where: str, a: str, key: str = "security.osc_allow") -> ipaddress.IPv4Network | ipaddress.IPv6Network:
    try:
        return ipaddress.ip_network(a.strip(), strict=False)
    except ValueError:
        raise SecurityError(f"{where}: {key} entry {a!r} is not an IP address or network "
                            f"(like 192.168.10.7 or 192.168.10.0/24)") from None


def address_allowed(addr: str, nets: list[Any] | None) -> bool:
    """Is source address ``addr`` in ``nets`` (None: no list, everyone)?"""
    if nets is None:
        return True
    try:
        ip = ipaddress.ip_address(str(addr).split("%")[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return any(ip in n for n in nets)


def apply_config(cfg: Any, raw: Any, where: str = "<config>", base: str | None = None) -> None:
    """Config validation hook: parse ``[security]`` into ``cfg.security`` and refuse exposure
    without authentication (``cfg`` is a daemon.config.Config with its endpoints parsed)."""
    cfg.security = parse_config(raw, where, base)
    check_exposure({"zmq.router": cfg.zmq_router, "zmq.pull": cfg.zmq_pull, "zmq.pub": cfg.zmq_pub},
                   cfg.osc_listen, cfg.security, where)
    cfg.metrics_networks = None
    if cfg.metrics_allow is not None:
        cfg.metrics_networks = [_network(where, a, "metrics.allow") for a in cfg.metrics_allow]
    if cfg.metrics_http is not None and not host_is_loopback(cfg.metrics_http[0]) and cfg.metrics_networks is None:
        # the endpoint names streams and models and has no authentication: the same rule as OSC
        raise SecurityError(
            f"{where}: metrics.http = \"{cfg.metrics_http[0]}:{cfg.metrics_http[1]}\" is not a loopback address and "
            f"the metrics endpoint has no authentication: set metrics.allow to the scrapers' addresses "
            f"(e.g. [\"192.168.10.5\"]), or bind 127.0.0.1")


# ---- the exposure rule ------------------------------------------------------------------------
def host_is_loopback(host: str) -> bool:
    """True only for a loopback IP literal or a loopback name; ``*``, ``0.0.0.0``, interface names
    and other host names count as exposed (a name could resolve anywhere)."""
    h = host.strip().strip("[]")
    if h.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(h.split("%")[0]).is_loopback
    except ValueError:
        return False


def endpoint_is_local(endpoint: str) -> bool:
    """``tcp://HOST:PORT`` on loopback, or a non-network transport (``ipc://``, ``inproc://``)."""
    if endpoint.startswith(("ipc://", "inproc://")):
        return True
    if endpoint.startswith("tcp://"):
        rest = endpoint[len("tcp://"):]
        host = rest.rpartition(":")[0] if ":" in rest else rest
        # tcp://src;dst form (bind source for connects): judge the part we bind or talk to
        host = host.split(";")[-1]
        return host_is_loopback(host)
    return False  # pgm://, epgm://, ws://... are network transports


def check_exposure(bound: dict[str, str | None], osc_listen: tuple[str, int] | None, spec: SecuritySpec,
                   where: str = "<config>") -> None:
    """Refuse a config that exposes the daemon without authentication.

    bound : {"zmq.router": endpoint or None, ...} the ZeroMQ endpoints the daemon *binds*.
    Raises SecurityError naming the endpoint; also checks the key files when CURVE is on.
    """
    exposed = {k: ep for k, ep in bound.items() if ep and not endpoint_is_local(ep)}
    if exposed and not spec.curve:
        k, ep = next(iter(exposed.items()))
        raise SecurityError(
            f"{where}: {k} = {ep!r} is not a loopback address, so ZeroMQ CURVE authentication is required: set "
            f"security.server_secret_key and security.authorized_keys (make keys with `lacuna keys DIR --name "
            f"server`), or bind 127.0.0.1")
    if osc_listen is not None and not host_is_loopback(osc_listen[0]) and spec.osc_networks is None:
        raise SecurityError(
            f"{where}: osc.listen = \"{osc_listen[0]}:{osc_listen[1]}\" is not a loopback address and OSC has no "
            f"authentication: set security.osc_allow to the senders' addresses (e.g. [\"192.168.10.0/24\"]), "
            f"or listen on 127.0.0.1")
    if spec.curve:
        if not zmq.has("curve"):
            raise SecurityError(f"{where}: [security] keys are set but this libzmq was built without CURVE "
                                f"(zmq.has('curve') is False); install a pyzmq wheel, which bundles it")
        load_server_key(spec.server_secret_key)  # type: ignore[arg-type]
        load_authorized(spec.authorized_keys)  # type: ignore[arg-type]
        if spec.operator_keys:
            load_authorized(spec.operator_keys)
    if spec.sub_server_key:
        load_public_key(spec.sub_server_key)


# ---- key files ----------------------------------------------------------------------------------
def _check_private(path: str) -> None:
    try:
        st = os.stat(path)
    except OSError as e:
        raise SecurityError(f"{path}: cannot read secret key file ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):  # (a FIFO would block the reload that opens it)
        raise SecurityError(f"{path}: secret key path is {kind_of(st.st_mode)}, not a regular file")
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SecurityError(f"{path}: secret key file is accessible by group/others (mode "
                            f"{stat.S_IMODE(st.st_mode):04o}); run chmod 600 {path}")


def load_server_key(path: str) -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys from a ``.key_secret`` file.  Raises SecurityError."""
    _check_private(path)
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as e:
        raise SecurityError(f"{path}: not a ZeroMQ certificate ({e})") from None
    if not secret:
        raise SecurityError(f"{path}: holds no secret key (this is a public .key file; use the .key_secret one)")
    return public, secret


def load_public_key(path: str) -> bytes:
    try:
        check_regular(path)
        public, _ = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as e:
        raise SecurityError(f"{path}: not a ZeroMQ public key file ({e})") from None
    return public


def load_authorized(directory: str) -> dict[bytes, bool]:
    """Public keys of the clients allowed in: every ``*.key`` file in ``directory``."""
    if not os.path.isdir(directory):
        raise SecurityError(f"{directory}: authorized_keys must be a directory of client public .key files")
    try:
        for f in glob.glob(os.path.join(directory, "*.key")):
            check_regular(f)  # a FIFO named *.key would block load_certificates
        keys = zmq.auth.load_certificates(directory)
    except (OSError, ValueError) as e:
        raise SecurityError(f"{directory}: cannot read the authorized client keys ({e})") from None
    if not keys:
        raise SecurityError(f"{directory}: holds no *.key files, so no client could connect "
                            f"(copy each client's public .key file there)")
    return keys


def configure_client(sock: zmq.Socket[Any], client_secret_file: str, server_public_file: str) -> None:
    """Make ``sock`` a CURVE client: its own key pair, and the server's public key to expect."""
    public, secret = load_server_key(client_secret_file)
    sock.curve_publickey = public
    sock.curve_secretkey = secret
    sock.curve_serverkey = load_public_key(server_public_file)


def _operators(directory: str | None) -> set[str]:
    if not directory:
        return set()
    return {k.decode("ascii") if isinstance(k, bytes) else str(k) for k in load_authorized(directory)}


# ---- the running guard ----------------------------------------------------------------------------
class _CountingAuthenticator(ThreadAuthenticator):
    """ThreadAuthenticator that counts its decisions (the daemon reports them in status)."""

    def __init__(self, context: zmq.Context[Any]):
        super().__init__(context)
        self.allowed = 0
        self.denied = 0

    def _send_zap_reply(self, request_id: Any, status_code: Any, status_text: Any,
                        user_id: Any = "anonymous") -> None:
        if status_code == b"200":
            self.allowed += 1
        else:
            self.denied += 1
        super()._send_zap_reply(request_id, status_code, status_text, user_id)


class Guard:
    """Applies a SecuritySpec to the daemon's sockets and checks OSC senders.

    ``server(sock)`` before ``bind``; ``client(sock)`` before the SUB socket connects;
    ``osc_allowed(addr)`` for every datagram; ``reload(spec)`` on SIGHUP; ``info()`` for status.
    """

    def __init__(self, ctx: zmq.Context[Any], spec: SecuritySpec | None):
        self.ctx = ctx
        self.spec = spec or SecuritySpec()
        self.osc_denied = 0
        self._lock = threading.Lock()
        self.auth: _CountingAuthenticator | None = None
        self._keys: tuple[bytes, bytes] | None = None
        self.operators: set[str] = set()  # Z85 public keys
        if self.spec.curve:
            self._keys = load_server_key(self.spec.server_secret_key)  # type: ignore[arg-type]
            allowed = load_authorized(self.spec.authorized_keys)  # type: ignore[arg-type]
            self.auth = _CountingAuthenticator(ctx)
            self.auth.start()
            self.auth.certs[ZAP_DOMAIN] = allowed
            self.operators = _operators(self.spec.operator_keys)

    def is_operator(self, key: str) -> bool:
        return key in self.operators

    def server(self, sock: zmq.Socket[Any]) -> None:
        if self._keys is None:
            return
        sock.curve_publickey, sock.curve_secretkey = self._keys
        sock.zap_domain = ZAP_DOMAIN.encode()
        sock.curve_server = True

    def client(self, sock: zmq.Socket[Any]) -> None:
        if not self.spec.sub_server_key:
            return
        if self._keys is None:
            raise SecurityError("security.sub_server_key needs the daemon's own key pair (security.server_secret_key)")
        sock.curve_publickey, sock.curve_secretkey = self._keys
        sock.curve_serverkey = load_public_key(self.spec.sub_server_key)

    def osc_allowed(self, addr: tuple[Any, ...]) -> bool:
        nets = self.spec.osc_networks
        if nets is None:
            return True
        try:
            ip = ipaddress.ip_address(str(addr[0]).split("%")[0])
        except ValueError:
            ok = False
        else:
            if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
                ip = ip.ipv4_mapped
            ok = any(ip in n for n in nets)
        if not ok:
            self.osc_denied += 1
        return ok

    def reload(self, spec: SecuritySpec | None) -> list[str]:
        """SIGHUP: re-read the authorized keys directory and replace the OSC allow list.  The
        daemon's own key pair and the sockets' mechanism change only on restart; returns the
        keys whose change was not applied."""
        spec = spec or SecuritySpec()
        skipped = [f"security.{k}" for k in ("server_secret_key", "sub_server_key")
                   if getattr(spec, k) != getattr(self.spec, k)]
        authorized = self.spec.authorized_keys
        if self.auth is not None:
            if spec.authorized_keys is None:
                skipped.append("security.authorized_keys")  # CURVE stays on until restart
            else:
                keys = load_authorized(spec.authorized_keys)  # raises before anything changes
                ops = _operators(spec.operator_keys)
                self.auth.certs[ZAP_DOMAIN] = keys
                self.operators = ops
                authorized = spec.authorized_keys
        self.spec = SecuritySpec(self.spec.server_secret_key, authorized, spec.osc_allow, self.spec.sub_server_key,
                                 spec.operator_keys, spec.osc_networks)
        return skipped

    def info(self) -> dict[str, Any]:
        d: dict[str, Any] = {"curve": self.spec.curve, "osc_allow": self.spec.osc_allow, "osc_denied": self.osc_denied}
        if self.auth is not None:
            d.update(auth_allowed=self.auth.allowed, auth_denied=self.auth.denied,
                     authorized_keys=len(self.auth.certs.get(ZAP_DOMAIN, {})), operator_keys=len(self.operators))
        return d

    def close(self) -> None:
        if self.auth is not None:
            self.auth.stop()
            self.auth = None
