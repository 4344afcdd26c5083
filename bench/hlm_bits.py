"""Every output of the HLM's compiled paths on real motion, written by one source tree and
compared bit for bit with another's (issue 19: a speed change to ``hlm.fast`` / ``hlm.condfill``
must keep the bits; bench/notebook/hlm64-6.md).

``dump`` (run with PYTHONPATH=TREE, so that TREE's code steps): 300 bundled ticks of 64 streams
37 frames apart at scattered pool rows handed over out of order (``step_block``: hlm.fast's
one-call batch and condfill.correct1), the mask changing every 20 ticks (the left arm missing:
the echo bench's case; legs only: the Sigma branch of the correction; 20% missing at random;
every third stream's arm), 200 steps of a lone stream (``step_slot``) and 100 of the
feature-space path (``stream.step``: ``hlm.fast.step`` + ``condfill.correct_many``), then the
state pool (posteriors, stream-cycle statistics).  Frames: CMU 35_08 (a bench take).
``compare``: the two files' arrays, byte for byte.

    PYTHONPATH=/tmp/main .venv/bin/python bench/hlm_bits.py dump MODEL.npz /tmp/a.npz
    PYTHONPATH=. .venv/bin/python bench/hlm_bits.py dump MODEL.npz /tmp/b.npz
    .venv/bin/python bench/hlm_bits.py compare /tmp/a.npz /tmp/b.npz

``dump MODEL OUT --ll-legs`` (a tree with ``HLMModel.set_ll_feats``, loco-14): with the "ll" row's partial
normaliser on the legs' features.  ``compare`` of a 2-column "ll" row against a 4-column one compares the
first two columns.
"""
from __future__ import annotations

import sys

import numpy as np

ARM = ("lhumerus", "lradius", "lwrist", "lhand")
LEGS = ("lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes")


def dump(model_path: str, out_path: str, ll_legs: bool = False) -> None:
    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    model = load_model(model_path)
    ch = model.channels
    take = load_trial("35_08")
    frames = take.frames[:, take.index(ch)].astype(np.float64)
    T, C = frames.shape
    rng = np.random.default_rng(1)
    arm = np.array([c.split(".")[0] in ARM for c in ch])
    legs = np.array([c.split(".")[0] in LEGS for c in ch])
    if ll_legs:   # the "ll" row's partial normaliser on the legs' features (loco-14; a tree with set_ll_feats)
        model.set_ll_feats(model.leg_feats(np.flatnonzero(legs)))
    n = 64
    streams = [model.stream() for _ in range(2 * n)][::2]
    order = rng.permutation(n)
    offs = np.arange(n) * 37
    acc: dict[str, list[np.ndarray]] = {k: [] for k in ("frame", "std", "style", "phase")}
    for t in range(300):
        kind = (t // 20) % 4
        if kind == 0:
            o = np.broadcast_to(~arm, (n, C)).copy()
        elif kind == 1:
            o = np.broadcast_to(legs, (n, C)).copy()
        elif kind == 2:
            o = rng.random((n, C)) > 0.2
        else:
            o = np.ones((n, C), bool)
            o[::3] = ~arm
        r = (offs + t) % T
        bf = model.step_block([streams[i] for i in order], np.where(o, frames[r], np.nan), o)
        for k in acc:
            acc[k].append(np.asarray(getattr(bf, k)))
    out = {"block_" + k: np.array(v) for k, v in acc.items()}
    s = model.stream()
    lone = []
    for t in range(200):
        o = ~arm if (t // 30) % 2 else (legs if t % 7 else np.ones(C, bool))
        fl = model.step_batch([s], np.where(o, frames[(t * 3) % T], np.nan)[None], o[None])[0]
        lone.append(np.concatenate([fl.frame, fl.std, fl.extras["style"], [fl.extras["phase"]]]))
    out["lone"] = np.array(lone)
    s = model.stream()
    feat = []
    for t in range(100):
        o = ~arm if t % 2 else legs
        fl = s.step(np.where(o, frames[t], np.nan), o)
        feat.append(np.concatenate([fl.frame, fl.std, fl.extras["style"], [fl.extras["phase"]]]))
    out["feature"] = np.array(feat)
    for k, v in model.pool.core.items():
        out["pool_" + k] = np.asarray(v)
    np.savez(out_path, **out)
    print(f"{out_path}: {', '.join(f'{k} {v.shape}' for k, v in out.items())}")


def compare(a_path: str, b_path: str) -> bool:
    a, b = np.load(a_path), np.load(b_path)
    same = sorted(a.files) == sorted(b.files)
    for k in a.files:
        x, y = a[k], b[k] if k in b.files else None
        if k == "pool_ll" and y is not None and x.shape[1:] != y.shape[1:] and x.shape[0] == y.shape[0]:
            w = min(x.shape[1], y.shape[1])   # (a tree before loco-14 keeps 2 columns, after it 4: the first 2 compared)
            print(f"pool_ll: {x.shape[1]} vs {y.shape[1]} columns, the first {w} compared")
            x, y = np.ascontiguousarray(x[:, :w]), np.ascontiguousarray(y[:, :w])
        ok = y is not None and x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()
        same &= ok
        if not ok:
            print(f"differs: {k}" + ("" if y is None or x.shape != y.shape else
                                     f" (max |a - b| {np.nanmax(np.abs(x.astype(float) - y.astype(float))):.3g})"))
    print("bit-equal" if same else "DIFFERENT")
    return same


if __name__ == "__main__":
    if len(sys.argv) in (4, 5) and sys.argv[1] == "dump" and sys.argv[4:] in ([], ["--ll-legs"]):
        dump(sys.argv[2], sys.argv[3], sys.argv[4:] == ["--ll-legs"])
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(0 if compare(sys.argv[2], sys.argv[3]) else 1)
    else:
        sys.exit(__doc__)
