"""`lacuna keys DIR [--name NAME]`: make a CURVE key pair for the daemon or for a client.

Writes ``DIR/NAME.key`` (public, safe to copy: put clients' ones in the daemon's
``authorized_keys`` directory, give the server's one to clients) and ``DIR/NAME.key_secret``
(secret, mode 0600, never leaves the machine it was made on).  The files are created under a
0077 umask, so the secret key is never readable by others even for an instant, and an existing
pair is never overwritten unless ``--force`` is given (replacing a key locks its holders out).
"""
from __future__ import annotations

import argparse
import os
import re
import stat

import zmq.auth

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def add_commands(cli) -> None:
    p = cli.command("keys", help="make a CURVE key pair (NAME.key public, NAME.key_secret secret, mode 0600)")
    p.add_argument("dir", metavar="DIR", help="directory for the key files (created mode 0700 if missing)")
    p.add_argument("--name", default="server", help="key pair name, e.g. server or a client's name (default server)")
    p.add_argument("--force", action="store_true", help="overwrite an existing key pair of that name")
    p.set_defaults(func=run)


def make_keys(directory: str, name: str = "server", force: bool = False) -> tuple[str, str]:
    """Create the pair; returns (public file, secret file).  Raises ValueError on bad names or
    when the pair exists and ``force`` is false."""
    if not NAME_RE.match(name):
        raise ValueError(f"--name must be 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit "
                         f"(got {name!r})")
    public = os.path.join(directory, f"{name}.key")
    secret = os.path.join(directory, f"{name}.key_secret")
    existing = [f for f in (public, secret) if os.path.exists(f)]
    if existing and not force:
        raise ValueError(f"{existing[0]} exists; refusing to overwrite a key pair (its holders would be locked out). "
                         f"Use --force to replace it")
    old = os.umask(0o077)
    try:
        os.makedirs(directory, mode=0o700, exist_ok=True)
        for f in existing:
            os.remove(f)  # create_certificates opens with "w"; a fresh file gets the 0077 umask
        pub, sec = zmq.auth.create_certificates(directory, name)
    finally:
        os.umask(old)
    os.chmod(sec, stat.S_IRUSR | stat.S_IWUSR)
    os.chmod(pub, 0o644)  # public by design
    return pub, sec


def run(args: argparse.Namespace) -> int:
    pub, sec = make_keys(args.dir, args.name, args.force)
    print(f"public key: {pub}")
    print(f"secret key: {sec} (mode 0600; keep it on this machine)")
    return 0
