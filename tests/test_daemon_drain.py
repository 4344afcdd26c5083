"""The transport's drain of a ROUTER ends without a failing recv (daemon/transport.py ``receive``):
after the message the poll announced, it reads while ZeroMQ's EVENTS says one is waiting, so no
``zmq.Again`` is raised (built in Python, it cost ~30 us of a cold 64-stream turn:
bench/notebook/floor-7.md), and every message waiting is still read in the same call."""
from __future__ import annotations

import sys

import msgpack
import zmq

from daemon import config, loop


def _again_raised(fn) -> int:
    """How many zmq.Again exceptions were raised in Python frames while ``fn`` ran."""
    seen = [0]

    def tracer(frame, event, arg):
        if event == "exception" and issubclass(arg[0], zmq.Again):
            seen[0] += 1
        return tracer

    sys.settrace(tracer)
    try:
        fn()
    finally:
        sys.settrace(None)
    return seen[0]


def test_drain_reads_every_waiting_message_without_a_failing_recv():
    cfg = config.from_dict({"daemon": {"max_streams": 8, "log_level": "error"},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = loop.Daemon(cfg)
    d.start()
    ctx = zmq.Context()  # (its own, ended below: other tests count this process's ZeroMQ threads)
    peer = ctx.socket(zmq.DEALER)
    try:
        peer.connect(d.endpoints()["router"])
        status = msgpack.packb({"v": 1, "type": "control", "cmd": "status"}, use_bin_type=True)
        for _ in range(3):
            peer.send(status)
        net = d.net
        assert net is not None
        reads = 0
        raised = 0
        while d.metrics.counters.get("messages_in", 0) < 3:
            ready = net.poll(5000)
            assert ready, "the messages never arrived"
            raised += _again_raised(lambda: net.receive(ready))
            reads += 1
        assert d.metrics.counters["messages_in"] == 3
        assert raised == 0, f"{raised} failing recv(s) in {reads} drain(s)"
        replies = 0
        while replies < 3 and peer.poll(5000):
            assert msgpack.unpackb(peer.recv())["type"] == "control-reply"
            replies += 1
        assert replies == 3
    finally:
        peer.close(0)
        ctx.term()
        d.close()
