"""`lacuna keys DIR [--name NAME]`: make a CURVE key pair for the daemon or for a client.

Writes ``DIR/NAME.key`` (public, safe to copy: put clients' ones in the daemon's
``authorized_keys`` directory, give the server's one to clients) and ``DIR/NAME.key_secret``
(secret, mode 0600, never leaves the machine it was made on).  The files are created with their
final mode (the secret key is never readable by others even for an instant), exclusively and
without following symlinks, and an existing pair (or a symlink at its path) is never
overwritten unless ``--force`` is given (replacing a key locks its holders out).
"""
from __future__ import annotations

import argparse
import datetime
import os
import re
import stat
from typing import Any

import zmq

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def add_commands(cli: Any) -> None:
    p = cli.command("keys", help="make a CURVE key pair (NAME.key public, NAME.key_secret secret, mode 0600)")
    p.add_argument("dir", metavar="DIR", help="directory for the key files (created mode 0700 if missing)")
    p.add_argument("--name", default="server", help="key pair name, e.g. server or a client's name (default server)")
    p.add_argument("--force", action="store_true", help="overwrite an existing key pair of that name")
    p.set_defaults(func=run)


def make_keys(directory: str, name: str = "server", force: bool = False) -> tuple[str, str]:
    """Create the pair; returns (public file, secret file).  Raises ValueError on bad names or
    when the pair exists and ``force`` is false.

    Each file is created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` and its final mode: a file, a
    symlink (dangling or not) or anything else already at the path is never written through
    (``--force`` removes what is there, a link itself and not its target, then creates)."""
    if not NAME_RE.match(name):
        raise ValueError(f"--name must be 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit "
                         f"(got {name!r})")
    public = os.path.join(directory, f"{name}.key")
    secret = os.path.join(directory, f"{name}.key_secret")
    existing = [f for f in (public, secret) if os.path.lexists(f)]  # (lexists: a dangling symlink counts)
    if existing and not force:
        what = "is a symlink" if os.path.islink(existing[0]) else "exists"
        raise ValueError(f"{existing[0]} {what}; refusing to overwrite a key pair (its holders would be locked out). "
                         f"Use --force to replace it")
    old = os.umask(0o077)
    try:
        os.makedirs(directory, mode=0o700, exist_ok=True)
        for f in existing:
            os.remove(f)
        pub_key, sec_key = zmq.curve_keypair()
        _write_new(secret, _cert(pub_key, sec_key), stat.S_IRUSR | stat.S_IWUSR)
        _write_new(public, _cert(pub_key, None), 0o644)  # public by design
    finally:
        os.umask(old)
    return public, secret


def _cert(public: bytes, secret: bytes | None) -> bytes:
    """ZeroMQ's certificate format (what zmq.auth.load_certificate reads)."""
    kind = "Secret" if secret else "Public"
    lines = [f"#   ****  Generated on {datetime.datetime.now()} by lacuna keys  ****",
             f"#   ZeroMQ CURVE **{kind}** Certificate",
             "#   DO NOT PROVIDE THIS FILE TO OTHER USERS nor change its permissions." if secret else
             "#   Exchange securely, or use a secure mechanism to verify the contents", "", "metadata", "curve",
             f'    public-key = "{public.decode()}"']
    if secret:
        lines.append(f'    secret-key = "{secret.decode()}"')
    return ("\n".join(lines) + "\n").encode()


def _write_new(path: str, data: bytes, mode: int) -> None:
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    except FileExistsError:
        raise ValueError(f"{path} appeared while the keys were made (a file or symlink); refusing to write "
                         f"through it") from None
    try:
        os.fchmod(fd, mode)  # (the umask may have taken bits of a public file's 0644)
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
    finally:
        os.close(fd)


def run(args: argparse.Namespace) -> int:
    pub, sec = make_keys(args.dir, args.name, args.force)
    print(f"public key: {pub}")
    print(f"secret key: {sec} (mode 0600; keep it on this machine)")
    return 0
