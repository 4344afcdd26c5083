"""lacuna fill and distributed training on a real Dask cluster: a ``dask scheduler`` and two
``dask worker`` processes on loopback, started here (tests/dask_cluster.py)."""
from __future__ import annotations

import glob
import json
import os
import signal

import numpy as np
import pytest
from dask_cluster import dask_cluster

from archive.formats import FILL_SUFFIX, read_fill_sidecar, std_decode
from lacuna.cli import main

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

# a few real takes of three formats and four performers
TAKES = ["cmu/07/07_02.amc", "cmu/35/35_01.amc", "cmu_li/walking_13.amc", "bvh/08_02.bvh"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with dask_cluster(2, str(tmp_path_factory.mktemp("dask-logs"))) as c:
        yield c


def _read(path):
    from archive.takes import read_with_gaps

    return read_with_gaps(str(path))[0].frames


def _same_outputs(a, b, rels):
    for rel in rels:
        fa, fb = _read(os.path.join(a, rel)), _read(os.path.join(b, rel))
        np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
        sa, sb = read_fill_sidecar(os.path.join(a, rel) + FILL_SUFFIX), read_fill_sidecar(os.path.join(b, rel) + FILL_SUFFIX)
        assert sa["filled"] == sb["filled"] and sa["values_filled"] == sb["values_filled"] > 0, rel
        np.testing.assert_allclose(std_decode(sa, sa["channels"]), std_decode(sb, sb["channels"]), atol=1e-12)


def test_cluster_fill_equals_local_fill(data, tmp_path, cluster):
    from archive.formats import MASK_SUFFIX, write_mask
    from mocap.bvh import read_bvh

    takes = [os.path.join(data, t) for t in TAKES[:-1]]
    # the BVH skeleton's bones are not CMU's, so --drop gaps erases nothing there: its gaps come
    # from a mask sidecar beside it (the take itself linked in)
    bvh = tmp_path / "08_02.bvh"
    os.symlink(os.path.join(data, TAKES[-1]), bvh)
    m = read_bvh(str(bvh))
    miss = np.zeros(m.frames.shape, bool)
    miss[40:100, 10:16] = True
    write_mask(str(bvh) + MASK_SUFFIX, miss, m.channels)
    takes.append(str(bvh))
    base = ["--method", "interp", "--drop", "gaps", "-q"]
    assert main(["fill", *takes, "--out", str(tmp_path / "local"), "--workers", "0", *base]) == 0
    js = tmp_path / "s.json"
    assert main(["fill", *takes, "--out", str(tmp_path / "cluster"), "--scheduler", cluster.address,
                 "--json", str(js), *base]) == 0
    s = json.loads(js.read_text())
    assert s["summary"]["filled"] == 4 and s["summary"]["workers"] == 2
    # the takes really ran on the workers, not here
    assert {r["pid"] for r in s["takes"]} <= set(cluster.client.run(os.getpid).values())
    _same_outputs(tmp_path / "local", tmp_path / "cluster", [os.path.basename(t) for t in TAKES])


def test_cluster_fill_with_a_model_ships_it_once(data, tmp_path, cluster):
    """A small HLM (trained here in seconds) filling with its default, the smoother (hlm-offline)."""
    from hlm.methods import train_model
    from mocap.asf import read_amc

    ms = [read_amc(os.path.join(data, f"cmu/07/07_{t}.amc")) for t in ("09", "10")]
    model = train_model([m.frames for m in ms], ms[0].channels, styles=1, cycle_frames=30, n_iter=2, restarts=1)
    model.meta["training"]["fps"] = 120.0
    mf = tmp_path / "hlm.npz"
    model.save(str(mf))
    takes = [os.path.join(data, "cmu/07/07_02.amc"), os.path.join(data, "cmu/35/35_01.amc")]
    base = ["--model", str(mf), "--drop", "gaps", "-q"]
    assert main(["fill", *takes, "--out", str(tmp_path / "local"), "--workers", "0", *base]) == 0
    js = tmp_path / "s.json"
    assert main(["fill", *takes, "--out", str(tmp_path / "cluster"), "--scheduler", cluster.address,
                 "--json", str(js), *base]) == 0
    s = json.loads(js.read_text())
    assert s["summary"]["method"] == "hlm-offline" and s["summary"]["filled"] == 2
    side = read_fill_sidecar(str(tmp_path / "cluster" / "07_02.amc") + FILL_SUFFIX)
    assert side["model"]["sha256"] == s["summary"]["model_sha256"] and side["method"] == "hlm-offline"
    _same_outputs(tmp_path / "local", tmp_path / "cluster", ["07_02.amc", "35_01.amc"])


def _many_takes(data, d, n):
    """n distinct take files (links to real takes; distinct names so each is its own output)."""
    d.mkdir()
    os.symlink(os.path.join(data, "cmu/35/35.asf"), d / "35.asf")
    src = sorted(glob.glob(os.path.join(data, "cmu/35/35_*.amc")))
    for i in range(n):
        os.symlink(src[i % len(src)], d / f"35_{i:03d}.amc")
    return d


def test_resumed_batch_does_only_what_was_missing(data, tmp_path, cluster):
    from archive.batch import run_batch
    from archive.fill import FillSpec
    from archive.takes import discover

    d = _many_takes(data, tmp_path / "in", 6)
    jobs = discover([str(d)], str(tmp_path / "out"))
    spec = FillSpec("hold")
    first = run_batch(jobs, spec, None, cluster.client, progress=False)
    assert len(first.rows) == 6 and not first.failed
    mt = {j.output: os.path.getmtime(j.output) for j in jobs}
    os.unlink(jobs[1].output)                       # an output lost
    os.unlink(jobs[4].output + FILL_SUFFIX)         # a take interrupted before its sidecar
    again = run_batch(jobs, spec, None, cluster.client, progress=False)
    assert sorted(r["index"] for r in again.rows) == [1, 4]
    assert len(again.skipped) == 4
    for j in jobs:
        if j.index not in (1, 4):
            assert os.path.getmtime(j.output) == mt[j.output]
    assert all(read_fill_sidecar(j.output + FILL_SUFFIX) for j in jobs)


def test_worker_killed_mid_batch_loses_no_take(data, tmp_path):
    from archive.batch import run_batch
    from archive.fill import FillSpec
    from archive.takes import discover

    d = _many_takes(data, tmp_path / "in", 16)
    jobs = discover([str(d)], str(tmp_path / "out"))
    with dask_cluster(2, str(tmp_path)) as c:
        pids = c.client.run(os.getpid)
        victim_addr = sorted(pids)[0]
        victim_pid = pids[victim_addr]
        nanny = c.worker_of_pid(victim_pid)
        killed: dict = {}

        def on_row(row):
            if killed or row.get("pid") != victim_pid:
                return
            # the take the victim is working on now: it must end up done by the other worker
            busy = c.client.processing(workers=[victim_addr]).get(victim_addr, [])
            killed["keys"] = list(busy)
            os.killpg(nanny.pid, signal.SIGKILL)

        res = run_batch(jobs, FillSpec("interp", drop="gaps"), None, c.client, progress=False, on_row=on_row)
    assert killed, "the victim worker never reported a take"
    assert killed["keys"], "the victim had no take in flight when it was killed"
    assert len(res.rows) == 16 and not res.failed, [r.get("error") for r in res.failed]
    lost = [int(k.rsplit("-", 1)[1]) for k in killed["keys"]]
    for i in lost:
        assert res.rows[i]["pid"] != victim_pid              # redone by the survivor
    for j in jobs:
        side = read_fill_sidecar(j.output + FILL_SUFFIX)
        assert side is not None and side["frames"] == _read(j.output).shape[0]
    assert not glob.glob(str(tmp_path / "out" / ".*.part"))   # no partial file left


def test_distributed_hlm_training_equals_local(data, cluster):
    from archive.hlm_dist import distributed_estep
    from hlm.methods import train_model
    from mocap.asf import read_amc
    from mocap.representation import resample

    ms = [read_amc(os.path.join(data, p)) for p in ("cmu/07/07_02.amc", "cmu/07/07_09.amc", "cmu/35/35_01.amc",
                                                    "cmu/35/35_06.amc", "cmu/35/35_17.amc")]
    seqs = [resample(m.frames, 120, 30, m.channels) for m in ms]
    kw = dict(styles=2, cycle_frames=35, n_iter=4, restarts=2)
    local = train_model(seqs, ms[0].channels, **kw)
    with distributed_estep(cluster.client) as mapper:
        dist = train_model(seqs, ms[0].channels, **kw)
    assert mapper.calls > 10 and mapper.n_chunks == 2
    bl, bd = np.array(local.meta["training"]["bounds"]), np.array(dist.meta["training"]["bounds"])
    np.testing.assert_allclose(bd, bl, rtol=1e-9, atol=0)
    for name in ("zbar", "mu", "var", "lam", "tau", "d"):
        np.testing.assert_allclose(getattr(dist.params, name), getattr(local.params, name), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(dist.params.lam_s, local.params.lam_s, rtol=1e-9)


def test_crbm_members_trained_on_workers_equal_local(data, cluster):
    from archive.crbm_dist import distributed_members
    from crbm.train import train_model
    from mocap.asf import read_amc
    from mocap.representation import resample

    ms = [read_amc(os.path.join(data, p)) for p in ("cmu/07/07_02.amc", "cmu/07/07_09.amc")]
    seqs = [resample(m.frames, 120, 30, m.channels) for m in ms]
    kw = dict(hidden=30, epochs=15, members=2, seed=3)
    local = train_model(seqs, ms[0].channels, **kw)
    with distributed_members(cluster.client):
        dist = train_model(seqs, ms[0].channels, **kw)
    assert len(dist.members) == 2
    for a, b in zip(local.members, dist.members):
        np.testing.assert_allclose(b.W_, a.W_, rtol=1e-12, atol=1e-12)
    assert not np.allclose(dist.members[0].W_, dist.members[1].W_)     # two seeds, two members


def test_train_commands_on_the_cluster_write_the_same_models(data, tmp_path, cluster):
    """`lacuna train hlm|crbm ... --scheduler ADDR` against the same commands in one process."""
    from lacuna.modelfile import load_arrays

    takes = [os.path.join(data, "cmu/07/07_02.amc"), os.path.join(data, "cmu/07/07_09.amc")]
    cmds = {"hlm": ["train", "hlm", *takes, "--styles", "1", "--cycle-frames", "30", "--iterations", "2",
                    "--restarts", "1", "-q"],
            "crbm": ["train", "crbm", *takes, "--members", "2", "--hidden", "20", "--epochs", "5", "-q"]}
    for what, cmd in cmds.items():
        assert main([*cmd, "-o", str(tmp_path / f"{what}-here.npz")]) == 0
        assert main([*cmd, "-o", str(tmp_path / f"{what}-cluster.npz"), "--scheduler", cluster.address]) == 0
        (_, a), (_, b) = load_arrays(str(tmp_path / f"{what}-here.npz")), load_arrays(str(tmp_path / f"{what}-cluster.npz"))
        assert sorted(a) == sorted(b)
        for k in a:
            np.testing.assert_allclose(b[k], a[k], rtol=1e-9, atol=1e-12, err_msg=f"{what} {k}")


def test_distributed_estep_with_missing_values_equals_local(data, cluster):
    """Training takes with gaps: eq. (18) refills them every M-step, so the frames travel with
    every E-step task; bound, parameters and the refilled values as in one process."""
    from archive.hlm_dist import distributed_estep
    from hlm.train import fit
    from mocap.asf import read_amc
    from mocap.representation import resample

    seqs = []
    for p in ("cmu/07/07_02.amc", "cmu/35/35_01.amc", "cmu/35/35_06.amc"):
        m = read_amc(os.path.join(data, p))
        seqs.append(resample(m.frames, 120, 30, m.channels)[:, 6:30].copy())   # legs and back
    seqs[0][20:40, 3:9] = np.nan
    seqs[2][5:15, 0:4] = np.nan
    kw = dict(n_styles=2, cycle_frames=35, n_restarts=1, n_iter=3)
    local = fit(seqs, **kw)
    with distributed_estep(cluster.client) as mapper:
        dist = fit(seqs, **kw)
    assert mapper.calls > 5
    np.testing.assert_allclose(dist.bounds, local.bounds, rtol=1e-9, atol=0)
    np.testing.assert_allclose(dist.params.mu, local.params.mu, rtol=1e-9, atol=1e-12)
    assert len(dist.filled) == 3
    for a, b in zip(local.filled, dist.filled):
        assert np.all(np.isfinite(b))
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)


def _session_of_this_process() -> tuple[int, int]:
    return os.getpid(), os.getsid(0)


def test_local_cluster_workers_each_lead_a_session_of_their_own():
    """Under the kernel's autogroup scheduling the CPU is shared between sessions: a local
    cluster's workers must not share the caller's (archive.cluster._own_session)."""
    from archive.cluster import open_client

    with open_client(workers=2) as client:
        got = client.run(_session_of_this_process)
    assert len(got) == 2
    for pid, sid in got.values():
        assert sid == pid != os.getsid(0)


def test_every_worker_warms_up_once_before_its_takes_with_one_thread_per_pool(data, tmp_path):
    """archive.warmup.warm runs as one task per worker ahead of the takes (imports and the model:
    no take's timers carry them), inside workers whose BLAS/OpenMP/numba pools have one thread."""
    from archive.batch import run_batch
    from archive.cluster import open_client
    from archive.fill import FillSpec
    from archive.takes import discover

    jobs = discover([str(data / t) for t in TAKES[:2]], str(tmp_path / "out"))
    with open_client(workers=2) as client:
        res = run_batch(jobs, FillSpec("interp", drop="gaps"), None, client, progress=False)
        pids = set(client.run(os.getpid).values())
    assert [r["status"] for r in res.rows] == ["filled", "filled"]
    assert sorted(w["pid"] for w in res.warm) == sorted(pids)      # one warm-up on each worker
    for w in res.warm:
        assert w["threads"] == {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                                "NUMBA_NUM_THREADS": "1"}
