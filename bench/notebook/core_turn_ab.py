"""CPU per frame of the pass-through path as the loop takes a turn (both trees have these):
_batch(the tick's messages) -> _serve() -> _answer_superseded(); frames from pan2009's first case."""
import json
import sys
import time

import numpy as np

sys.path.insert(0, "bench")
from daemon import config, wire
from daemon.models import load_all
from daemon.server import Daemon
from mocap.protocols import get_protocol

proto = get_protocol("pan2009")
ch = list(proto.training_set().channels)
frames = proto.cases()[0].truth.astype(np.float32)
cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "max_streams": 100000, "log_level": "warning"},
                        "models": {"floor": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
d = Daemon(cfg); t, e = load_all(cfg); d._install(t)
out = []
d._send = lambda o, m, publish=False: out.append(wire.encode(m))
res = {}
for n, bundle in ((1, False), (64, False), (64, True)):
    vals = []
    for rep in range(5):
        sids = [f"s{n}{bundle}{rep}-{i}" for i in range(n)]
        d._batch([(wire.encode(wire.Hello(s, ch)), ("router", [b"x"]), time.perf_counter()) for s in sids])
        ticks = max(20, 3000 // n)
        msgs = [[wire.encode(wire.Bundle([wire.Frame(s, k, k / 120, frames[k % len(frames)]) for s in sids]))] if bundle else
                [wire.encode(wire.Frame(s, k, k / 120, frames[k % len(frames)])) for s in sids] for k in range(ticks + 20)]
        for k in range(20):
            d._batch([(b, ("router", [b"x"]), time.perf_counter()) for b in msgs[k]]); d._serve(); d._answer_superseded()
        c0 = time.process_time()
        for k in range(20, ticks + 20):
            d._batch([(b, ("router", [b"x"]), time.perf_counter()) for b in msgs[k]]); d._serve(); d._answer_superseded()
        vals.append(1e6 * (time.process_time() - c0) / (ticks * n))
        for s in sids:
            d.sessions.reset(s)
        out.clear()
    res[f"{n}{' bundled' if bundle else ''}"] = round(float(np.median(vals)), 1)
print(json.dumps(res))
