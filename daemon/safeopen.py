"""Open a file the daemon reads (config, model, key) so that nothing at its path can wedge it.

``open()`` on a FIFO blocks until a writer appears, and on some devices forever: a config or
model path that pointed at one once wedged the reload thread until restart (every later
reload unanswered, SIGHUPs ignored).  Here the path is opened with ``O_NONBLOCK`` (which
returns at once for a FIFO, a device or a socket), ``fstat`` on the descriptor says what it
is, and anything but a regular file is refused with an error naming it.  The read then goes
through ``/proc/self/fd/N``, the very file that was checked (a rename in between cannot swap
in a FIFO), with blocking reads (O_NONBLOCK means nothing for a regular file).
"""
from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"))


class NotRegularFile(OSError):
    """The path exists but is not a regular file (FIFO, device, socket, directory)."""


def kind_of(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path: str) -> None:
    """``stat`` (never blocks) and refuse a non-regular file.  For files opened by other
    libraries (key files): a small window remains between this check and their ``open``."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise NotRegularFile(f"{path} is {kind_of(st.st_mode)}, not a regular file")


@contextmanager
def regular_fd(path: str) -> Iterator[int]:
    """An O_RDONLY descriptor of ``path``, opened without blocking and checked to be a regular
    file.  Raises NotRegularFile or the OSError of ``open``."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | getattr(os, "O_NOCTTY", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotRegularFile(f"{path} is {kind_of(st.st_mode)}, not a regular file")
        yield fd
    finally:
        os.close(fd)


def read_regular(path: str, limit: int = 1 << 30) -> bytes:
    """The bytes of a regular file, refusing anything else (see :func:`regular_fd`)."""
    with regular_fd(path) as fd:
        os.set_blocking(fd, True)
        chunks: list[bytes] = []
        n = 0
        while True:
            b = os.read(fd, 1 << 20)
            if not b:
                return b"".join(chunks)
            n += len(b)
            if n > limit:
                raise OSError(f"{path} is larger than {limit} bytes")
            chunks.append(b)


def proc_path(fd: int) -> str | None:
    """A path that opens the same file as ``fd`` (Linux), or None."""
    p = f"/proc/self/fd/{fd}"
    return p if os.path.exists(p) else None
