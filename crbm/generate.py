"""Generation from a trained CRBM (section 4): seed with a few real frames, then every frame is
fully missing and filled by the same clamped-Gibbs step with nothing clamped: start from the
previous frame plus noise, the past n frames set the dynamic biases, K alternating Gibbs
iterations, a final mean-field step.  Which motion comes out (walk or run, section 4.1) depends
only on the seed frames."""
from __future__ import annotations

import numpy as np

from crbm.filler import CRBMModel


def generate(model: CRBMModel, seed_frames: np.ndarray, n_frames: int, seed: int | None = 0,
             n_gibbs: int | None = None) -> np.ndarray:
    """seed_frames: (m, C) raw frames at the model's frame rate, m >= order + 1 recommended (the
    first frame carries no root motion).  Returns (m + n_frames, C) raw frames, seed included.

    The model is not changed: generation steps a ``variant`` of it (one chain, Gibbs sampling,
    the given seed and K) over the same trained arrays.
    """
    seed_frames = np.asarray(seed_frames, dtype=np.float64)
    if seed_frames.ndim != 2 or seed_frames.shape[1] != model.n_channels:
        raise ValueError(f"seed frames must be (m, {model.n_channels}) (got shape {seed_frames.shape})")
    if seed_frames.shape[0] < 1:
        raise ValueError("generation needs at least one seed frame")
    if not np.all(np.isfinite(seed_frames)):
        raise ValueError("seed frames contain NaN or infinity")
    if int(n_frames) != n_frames or n_frames < 0:
        raise ValueError(f"frames must be a non-negative integer (got {n_frames!r})")
    # one sample path (averaging chains would blur the motion)
    gen = model.variant(n_chains=1, mode="gibbs", seed=seed, n_gibbs=n_gibbs)
    st = gen.stream()
    out = [st.step(f).frame for f in seed_frames]
    for _ in range(int(n_frames)):
        out.append(st.predict().frame)
    return np.vstack(out)
