"""An ensemble's CRBM members trained on Dask workers, one task per member.

``crbm.train.train_model`` trains members one after another with ``crbm.train.fit_member``;
inside ``distributed_members(client)`` the same function runs on the workers instead.  Each
member has its own seed (``seed + MEMBER_SEED_STRIDE * i``) and sees the same features, which are
scattered once to every worker, so a member trained on a worker is the member trained here.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator

from crbm.train import fit_member, member_map


def _member_task(Z, i: int, kw: dict):
    from archive.worker import tune_malloc
    from lacuna.blas import single_thread_blas

    tune_malloc()
    with single_thread_blas():  # mini-batch products: a second BLAS thread only spins (lacuna.blas)
        m = fit_member(Z, i, **{**kw, "progress": False})
    m.progress = None
    return m


class DaskMembers:
    """A mapper for ``crbm.train.member_map``."""

    def __init__(self, client):
        self.client = client

    def __call__(self, Z, members: list[int], kw: dict) -> list:
        ref = self.client.scatter(list(Z), broadcast=True, hash=False)
        futures = [self.client.submit(_member_task, ref, i, kw, pure=False, retries=2) for i in members]
        return self.client.gather(futures)


@contextlib.contextmanager
def distributed_members(client) -> Iterator[DaskMembers]:
    mapper = DaskMembers(client)
    with member_map(mapper):
        yield mapper
