"""``--scheduler ADDR`` / ``--workers N`` for ``lacuna train hlm`` and ``lacuna train crbm``."""
from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def training_cluster(args, what: str) -> Iterator[None]:
    """Run the training inside the block on a Dask cluster when the command line asks for one:
    HLM's E-step over the takes (archive.hlm_dist), a CRBM ensemble's members (archive.crbm_dist)."""
    scheduler, workers = getattr(args, "scheduler", None), getattr(args, "workers", None)
    if not scheduler and workers is None:
        yield
        return
    from archive.cluster import describe, open_client

    with open_client(scheduler, workers) as client:
        info = describe(client)
        if not getattr(args, "quiet", False):
            print(f"{what}: training on {info['workers']} Dask workers at {info['scheduler']}", file=sys.stderr, flush=True)
        if what == "hlm":
            from archive.hlm_dist import distributed_estep as ctx
        else:
            from archive.crbm_dist import distributed_members as ctx
        with ctx(client):
            yield
