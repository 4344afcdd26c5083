"""Issue 7, item 1, decoder by decoder and in process: seeded mutations of real inputs must come
out as the decoder's own error type (a clear message naming what arrived) or as a valid result;
never another exception (which in the daemon would cost a loop iteration, in the CLI a traceback).

* wire.decode / osc.decode: bit flips, truncations and splices of valid messages -> WireError;
* config.load: mutated lines of the example systemd/lacuna.toml -> ConfigError;
* model files: byte-level corruption of a real model, and structure-level corruption (meta
  values, array shapes, dtypes, non-finite values) -> ModelFileError, checked before use;
* AMC, ASF, BVH, CSV readers: mutated real files -> ParseError naming the file (and line).
"""
from __future__ import annotations

import io
import json
import random
import zipfile
from pathlib import Path

import fuzzgen
import numpy as np
import pytest

from daemon import config, osc, wire
from daemon.config import ModelSpec
from daemon.models import load_one
from lacuna import modelfile
from lacuna.errors import LacunaError
from mocap import asf, bvh, csvio
from mocap.baselines import HoldModel, NearestNeighbourModel
from mocap.datasets import data_dir, load_trial

ROOT = Path(__file__).resolve().parents[1]
TOKENS = ["nan", "NaN", "inf", "-inf", "1e999", "-", "", "abc", "{", "}", "=", "[", "]", "\"", "ROOT", "JOINT",
          "End", "Site", "CHANNELS", "99999999999999999999", "-0", "0x10", "\u0661", "1.5.3", "\x00", ":root",
          "begin", "end", "order", "true", "[models.x]", "file = 5"]


def mutate_text(text: str, r: random.Random) -> str:
    lines = text.split("\n")
    for _ in range(r.randrange(1, 4)):
        op = r.randrange(7)
        i = r.randrange(len(lines)) if lines else 0
        if not lines:
            lines = [r.choice(TOKENS)]
        elif op == 0:
            del lines[i]
        elif op == 1:
            lines.insert(i, lines[r.randrange(len(lines))])
        elif op == 2:  # replace one whitespace-separated token
            parts = lines[i].split(" ")
            parts[r.randrange(len(parts))] = r.choice(TOKENS)
            lines[i] = " ".join(parts)
        elif op == 3:
            lines.insert(i, r.choice(TOKENS) + " " + r.choice(TOKENS))
        elif op == 4:
            j = r.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == 5:  # truncate the whole text
            return "\n".join(lines)[: r.randrange(len(text) + 1)]
        else:
            s = lines[i]
            if s:
                k = r.randrange(len(s))
                lines[i] = s[:k] + chr(r.randrange(32, 127)) + s[k + 1:]
    return "\n".join(lines)


# ---- wire and OSC --------------------------------------------------------------------------------
def test_wire_and_osc_decoders_raise_only_wire_errors(seed):
    r = random.Random(seed)
    gen = fuzzgen.Fuzz(seed, 8, 4096)
    valid_z = [gen._valid_zmq() for _ in range(50)] + [wire.encode(wire.Frame("s", 3, 1.0, np.ones(8, np.float32),
                                                                              np.ones(8, bool)))]
    valid_o = [fuzzgen.osc_frame("s", i, 0.5, np.arange(8.0)) for i in range(20)] + \
        [fuzzgen.osc_message("/lacuna/hello", [("s", "s"), ("s", ""), ("s", "a"), ("s", "b")]),
         fuzzgen.osc_message("/lacuna/frame/masked", [("s", "s"), ("i", 1), ("d", 0.0), ("b", b"\0" * 32),
                                                      ("b", b"\1" * 8)])]
    def bundle(*els: bytes) -> bytes:
        return osc.BUNDLE_PREFIX + b"\0" * 7 + b"\1" + b"".join(len(e).to_bytes(4, "big") + e for e in els)

    valid_b = [bundle(*r.sample(valid_o, r.randrange(1, 5))) for _ in range(20)] + \
        [bundle(valid_o[0], bundle(valid_o[1], bundle(valid_o[2])))]
    n = {"zmq": [0, 0], "osc": [0, 0], "osc bundle": [0, 0]}
    for kind, valid, dec in (("zmq", valid_z, wire.decode), ("osc", valid_o, osc.decode),
                             ("osc bundle", valid_b, osc.decode_bundle)):
        for _ in range(20_000):
            b = bytearray(r.choice(valid))
            op = r.randrange(4)
            if op == 0:
                for _ in range(r.randrange(1, 6)):
                    b[r.randrange(len(b))] = r.randrange(256)
            elif op == 1:
                b = b[: r.randrange(len(b))]
            elif op == 2:
                other = r.choice(valid)
                b = b[: r.randrange(len(b))] + other[r.randrange(len(other)):]
            else:
                k = r.randrange(len(b))
                b[k:k] = bytes(r.randrange(256) for _ in range(r.randrange(1, 16)))
            try:
                out = dec(bytes(b), 4096)
                bad = False
                if kind == "osc bundle":  # each element is a request or the WireError it raised, nothing else
                    assert all(isinstance(m, (wire.WireError, wire.Frame, wire.Hello, wire.Control)) for m in out)
                    errs = [m for m in out if isinstance(m, wire.WireError)]
                    assert all(e.reason and e.detail for e in errs)
                    bad = bool(errs)
                n[kind][1 if bad else 0] += 1
            except wire.WireError as e:
                assert e.reason and e.detail  # a stable code and a sentence
                n[kind][1] += 1
    assert all(rej > 1000 for _, rej in n.values())  # the mutations really produced bad input


# ---- config ----------------------------------------------------------------------------------------
def test_config_loader_raises_only_config_errors(tmp_path, seed):
    r = random.Random(seed)
    text = (ROOT / "systemd" / "lacuna.toml").read_text()
    text += '\n[security]\nosc_allow = ["127.0.0.1"]\n'
    p = tmp_path / "c.toml"
    p.write_text(text)
    config.load(str(p))  # the unmutated example is valid
    outcomes = {"ok": 0, "refused": 0}
    for _ in range(1500):
        p.write_text(mutate_text(text, r))
        try:
            config.load(str(p))
            outcomes["ok"] += 1
        except config.ConfigError as e:
            assert str(p) in str(e)  # names the file
            outcomes["refused"] += 1
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(config.ConfigError):
        config.load(str(p))
    assert outcomes["refused"] > 300


# ---- model files -------------------------------------------------------------------------------------
def _load(path: str):
    """The daemon's path: load, check, warm up (daemon.models.load_one); then a step must work."""
    m = load_one(ModelSpec("m", file=path), 4.0).model
    fill = m.stream().step(np.zeros(m.n_channels), np.ones(m.n_channels, bool))
    assert np.isfinite(fill.frame).all()
    return m


def test_model_files_are_checked_before_use(tmp_path, seed, data):
    r = random.Random(seed)
    motion = load_trial("35_01")
    path = str(tmp_path / "m.npz")
    good = {}
    for name, model in (("hold", HoldModel.fit([motion.frames], list(motion.channels))),
                        ("nn", NearestNeighbourModel.fit([motion.frames[:50]], list(motion.channels)))):
        model.save(path)
        good[name] = open(path, "rb").read()
        _load(path)
    refused = 0
    # byte level: flips, truncation, inserted bytes anywhere in the zip container
    for _i in range(400):
        b = bytearray(good[r.choice(list(good))])
        op = r.randrange(3)
        if op == 0:
            for _ in range(r.randrange(1, 4)):
                b[r.randrange(len(b))] ^= 1 << r.randrange(8)
        elif op == 1:
            b = b[: r.randrange(len(b))]
        else:
            k = r.randrange(len(b))
            b[k:k] = bytes(r.randrange(256) for _ in range(r.randrange(1, 64)))
        open(path, "wb").write(bytes(b))
        try:
            _load(path)
        except modelfile.ModelFileError as e:
            assert path in str(e)
            refused += 1
    assert refused > 300
    # structure level: a well-formed container holding the wrong things
    C = len(motion.channels)
    base_meta = {"method": "hold", "channels": list(motion.channels)}
    bad_cases = [
        ({"format_version": 2}, None), ({"format_version": "1"}, None), ({"format": "other"}, None),
        ({"channels": "root.tx"}, None), ({"channels": [1, 2]}, None), ({"method": None}, None),
        ({"method": "pickle"}, None), ({}, {"mean": np.zeros(C - 1), "std": np.ones(C)}),
        ({}, {"mean": np.zeros((C, 2)), "std": np.ones(C)}), ({}, {"std": np.ones(C)}),
        ({}, {"mean": np.full(C, np.inf), "std": np.ones(C)}), ({}, {"mean": np.array(["a"] * C), "std": np.ones(C)}),
        ({}, {"mean": np.zeros(C, complex) + np.nan * 1j, "std": np.ones(C)}),
        ({"method": "nn"}, {"train": np.zeros((0, C)), "scale": np.ones(C)}),
        ({"method": "nn"}, {"train": np.zeros((5, C)), "scale": np.full(C, np.nan)}),
    ]
    for meta, arrays in bad_cases:
        modelfile.save_arrays(path, {**base_meta, **meta}, arrays if arrays is not None else
                              {"mean": np.zeros(C), "std": np.ones(C)})
        with pytest.raises(modelfile.ModelFileError):
            _load(path)
    # a metadata entry that is not JSON, and an npz with no metadata at all
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.array("{not json"), mean=np.zeros(C))
    open(path, "wb").write(buf.getvalue())
    with pytest.raises(modelfile.ModelFileError, match="JSON"):
        _load(path)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("mean.npy", b"\x93NUMPY garbage")
    with pytest.raises(modelfile.ModelFileError):
        _load(path)
    json.dumps(bad_cases[0][0])  # (cases are plain data)


# ---- motion file readers -----------------------------------------------------------------------------
def _check_reader(parse, text: str, r: random.Random, n: int) -> int:
    refused = 0
    for _ in range(n):
        try:
            m = parse(mutate_text(text, r))
        except LacunaError as e:
            assert "<" in str(e) or ":" in str(e)  # names the source (and the line where it can)
            refused += 1
            continue
        assert m.frames.ndim == 2 and m.frames.shape[1] == len(m.channels)
    return refused


def test_amc_asf_bvh_csv_readers_raise_only_parse_errors(seed, data):
    r = random.Random(seed)
    d = data_dir()
    asf_text = (d / "cmu" / "35" / "35.asf").read_text()
    amc_lines = (d / "cmu" / "35" / "35_01.amc").read_text().split("\n")
    amc_text = "\n".join(amc_lines[: 3 + 29 * 12])  # header and the first dozen frames: fast to parse
    skel = asf.parse_asf(asf_text)
    bvh_lines = (d / "bvh" / "07_01.bvh").read_text().split("\n")
    hierarchy_end = next(i for i, l in enumerate(bvh_lines) if l.startswith("Frame Time"))  # noqa: E741
    bvh_text = "\n".join(bvh_lines[: hierarchy_end + 13]).replace(bvh_lines[hierarchy_end - 1],
                                                                     "Frames: 12", 1)
    m = bvh.parse_bvh(bvh_text)
    csv_text = csvio.format_csv(m)
    counts = {
        "asf": _check_reader(lambda t: _asf_as_motion(t), asf_text, r, 300),
        "amc": _check_reader(lambda t: asf.parse_amc(t, skel), amc_text, r, 400),
        "bvh": _check_reader(bvh.parse_bvh, bvh_text, r, 400),
        "csv": _check_reader(csvio.parse_csv, csv_text, r, 400),
    }
    assert all(v > 50 for v in counts.values()), counts


def _asf_as_motion(text: str):
    """parse_asf returns a Skeleton; wrap it so the reader check's shape test applies."""
    sk = asf.parse_asf(text)

    class _M:
        channels = sk.channels if hasattr(sk, "channels") else []
        frames = np.zeros((1, len(channels)))
    return _M
