"""Keep the CPUs from sleeping deeply while the daemon runs: a Linux PM QoS request.

A CPU that goes idle enters a C-state, and the deeper the state the longer it takes to wake
when a frame arrives; a virtual CPU that halts may be handed to another guest and comes back
with cold caches.  On the 2-core VM of docs/BENCHMARKS.md one HLM stream's frame took 576 us
of the daemon's time after an 8 ms wait against 65 us back to back, and 208 us with this request
held ("CPU cost per frame", `bench/daemon_hotpath.py --gap-ms 8`).  Writing a latency bound in microseconds to ``/dev/cpu_dma_latency``
asks the kernel to use no idle state whose exit latency exceeds it; ``0`` keeps every CPU in
its polling idle loop.  The request holds for as long as the file stays open and ends when it
is closed (or the process dies), so the daemon keeps it open for its lifetime.  This is what
tuned's ``latency-performance`` profile and ``cyclictest`` do.

The price: CPUs held out of sleep draw power and heat, and on a virtual machine they burn host
CPU.  It is a capture-box setting, off unless ``daemon.cpu_latency_us`` is set, and it affects
the whole machine (the kernel takes the smallest of all open requests).

The device is root-only (0600) on most distributions: systemd/lacuna.service says how to run the
daemon with it under systemd.  A request the daemon cannot make is logged and reported in
``status``; the daemon serves on without it.
"""
from __future__ import annotations

import os
import struct
from typing import Any

DEVICE = "/dev/cpu_dma_latency"
_S32 = struct.Struct("=i")  # the device takes and returns one native-endian signed 32-bit value


class CpuLatency:
    """One PM QoS CPU latency request, held open until :meth:`release`."""

    def __init__(self, device: str = DEVICE):
        self.device = device
        self.requested_us: int | None = None
        self.error: str | None = None
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def request(self, us: int | None) -> bool:
        """Hold a request of ``us`` microseconds (None: hold none).  Replaces any earlier
        request.  Returns whether it is held; on failure ``error`` says why."""
        self.release()
        self.requested_us, self.error = us, None
        if us is None:
            return False
        try:
            fd = os.open(self.device, os.O_RDWR | os.O_CLOEXEC)
        except OSError as e:
            self.error = f"cannot open {self.device}: {e.strerror or e}"
            return False
        try:
            if os.write(fd, _S32.pack(int(us))) != _S32.size:
                raise OSError(f"short write to {self.device}")
        except OSError as e:
            os.close(fd)
            self.error = f"cannot write {self.device}: {getattr(e, 'strerror', None) or e}"
            return False
        self._fd = fd
        return True

    def effective_us(self) -> int | None:
        """The bound the kernel applies now (the smallest of every process's requests), read
        back from the device; None when it cannot be read."""
        try:
            fd = os.open(self.device, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            return None
        try:
            b = os.read(fd, _S32.size)
        except OSError:
            return None
        finally:
            os.close(fd)  # a read-only open makes no request of its own
        return _S32.unpack(b)[0] if len(b) == _S32.size else None

    def info(self) -> dict[str, Any]:
        return {"requested_us": self.requested_us, "held": self.held, "device": self.device,
                "effective_us": self.effective_us() if self.held else None, "error": self.error}

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
