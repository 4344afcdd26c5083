"""What studio people touch: the plugin library, the OSC bridge, recorder, replay, benchmark, demo.

``clients.client.Client`` (blocking) and ``clients.aio.AsyncClient`` (asyncio) speak wire schema
v1 (``daemon/wire.py``, docs/PROTOCOL.md) to ``lacuna serve`` over ZeroMQ request/reply;
``clients.client.CaptureClient`` sends several performers' frames of one instant as one bundle.
"""
from clients.client import CaptureClient, Client
from clients.session import DaemonUnavailable

__all__ = ["CaptureClient", "Client", "DaemonUnavailable"]
