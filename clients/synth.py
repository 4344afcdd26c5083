"""A synthetic gait generator for offline demos (no data directory and no network).

It is NOT motion capture: it draws joint-angle curves of a walk on the CMU skeleton's 62
channels from a handful of sinusoids in the gait phase (hip flexion, knee flexion with its
stance-phase bump, ankle, counter-swinging arms, pelvis roll, head bob), each take with its own
cadence, stride amplitude, heading drift and a little AR(1) jitter.  It exists so that
``lacuna demo`` can show the whole path (train, serve, replay, score) on a machine that has
neither the CMU files nor a connection; numbers measured on it say nothing about real motion,
and the demo says so when it uses it.
"""
from __future__ import annotations

import numpy as np

from mocap.motion import Motion

FPS = 120.0

# The CMU skeleton's channels in the order of its ASF files (subjects 07 and 35).
CMU_CHANNELS = (
    ["root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz"]
    + [f"{b}.{d}" for b, ds in [("lfemur", "xyz"), ("ltibia", "x"), ("lfoot", "xz"), ("ltoes", "x"),
                                ("rfemur", "xyz"), ("rtibia", "x"), ("rfoot", "xz"), ("rtoes", "x"),
                                ("lowerback", "xyz"), ("upperback", "xyz"), ("thorax", "xyz"),
                                ("lowerneck", "xyz"), ("upperneck", "xyz"), ("head", "xyz"),
                                ("lclavicle", "yz"), ("lhumerus", "xyz"), ("lradius", "x"), ("lwrist", "y"),
                                ("lhand", "xz"), ("lfingers", "x"), ("lthumb", "xz"),
                                ("rclavicle", "yz"), ("rhumerus", "xyz"), ("rradius", "x"), ("rwrist", "y"),
                                ("rhand", "xz"), ("rfingers", "x"), ("rthumb", "xz")]
       for d in (f"r{a}" for a in ds)]
)


def _limb(phi: np.ndarray, a: float, side: str) -> dict[str, np.ndarray]:
    """One side's leg and arm curves; the right side runs half a cycle behind the left."""
    p = phi if side == "l" else phi + np.pi
    s = 1.0 if side == "l" else -1.0
    swing = np.sin(p)
    knee = 5.0 + a * (55.0 * np.clip(np.sin(p + 0.9), 0, None) ** 2 + 12.0 * np.clip(np.sin(p - 2.2), 0, None))
    return {
        f"{side}femur.rx": -8.0 - a * 24.0 * swing,
        f"{side}femur.ry": s * (4.0 + 3.0 * np.cos(p)),
        f"{side}femur.rz": s * (-6.0 + 2.5 * np.sin(p + 0.5)),
        f"{side}tibia.rx": knee,
        f"{side}foot.rx": -8.0 + a * 14.0 * np.sin(p - 0.8),
        f"{side}foot.rz": s * (-10.0 + 3.0 * np.cos(p)),
        f"{side}toes.rx": 5.0 + a * 18.0 * np.clip(np.sin(p - 1.7), 0, None) ** 2,
        f"{side}clavicle.ry": np.full_like(p, s * -15.0),
        f"{side}clavicle.rz": np.full_like(p, s * 10.0),
        f"{side}humerus.rx": -10.0 + a * 18.0 * np.sin(p + np.pi),
        f"{side}humerus.ry": s * (-12.0 + 4.0 * np.cos(p)),
        f"{side}humerus.rz": s * (-70.0 + 3.0 * np.sin(p)),
        f"{side}radius.rx": 25.0 + a * 12.0 * np.clip(np.sin(p + np.pi - 0.4), 0, None),
        f"{side}wrist.ry": s * (10.0 + 3.0 * np.sin(p)),
        f"{side}hand.rx": -15.0 + 4.0 * np.sin(p + 0.3),
        f"{side}hand.rz": s * (5.0 + 2.0 * np.cos(p)),
        f"{side}fingers.rx": np.full_like(p, 7.0),
        f"{side}thumb.rx": 10.0 + 2.0 * np.sin(p),
        f"{side}thumb.rz": s * (-30.0 + 2.0 * np.cos(p)),
    }


def gait(seconds: float = 6.0, seed: int = 0, fps: float = FPS, style: str = "walk") -> Motion:
    """One synthetic take.

    Returns
    -------
    Motion with ``frames`` of shape (round(seconds * fps), 62) on :data:`CMU_CHANNELS`.
    """
    rng = np.random.default_rng(seed)
    T = int(round(seconds * fps))
    t = np.arange(T) / fps
    fast = style == "run"
    period = rng.uniform(0.62, 0.72) if fast else rng.uniform(1.0, 1.2)  # seconds per gait cycle
    a = rng.uniform(0.85, 1.15) * (1.4 if fast else 1.0)  # stride amplitude
    phi = 2 * np.pi * t / period + rng.uniform(0, 2 * np.pi)
    speed = (40.0 if fast else 22.0) * a  # ASF length units per second (about 1.2 m/s walking)
    yaw = rng.uniform(-180, 180) + np.cumsum(np.full(T, rng.normal(0, 6.0) / fps))  # slow turn, degrees
    h = np.deg2rad(yaw)
    ch: dict[str, np.ndarray] = {
        "root.tx": np.cumsum(speed * np.sin(h)) / fps,
        "root.ty": 17.0 + 0.5 * a * np.cos(2 * phi),
        "root.tz": np.cumsum(speed * np.cos(h)) / fps,
        "root.rx": -2.0 + 1.5 * np.sin(2 * phi),
        "root.ry": (yaw + 180.0) % 360.0 - 180.0,
        "root.rz": 3.0 * a * np.sin(phi),
        "lowerback.rx": 4.0 + 1.5 * np.sin(2 * phi), "lowerback.ry": 2.0 * np.sin(phi), "lowerback.rz": 1.5 * np.cos(phi),
        "upperback.rx": 1.0 + 0.8 * np.sin(2 * phi), "upperback.ry": -2.5 * np.sin(phi), "upperback.rz": -1.0 * np.cos(phi),
        "thorax.rx": -1.0 + 0.5 * np.sin(2 * phi), "thorax.ry": -3.5 * np.sin(phi), "thorax.rz": -1.0 * np.cos(phi),
        "lowerneck.rx": -8.0 - 1.0 * np.sin(2 * phi + 0.5), "lowerneck.ry": 2.0 * np.sin(phi), "lowerneck.rz": 0.5 * np.cos(phi),
        "upperneck.rx": 12.0 + 1.0 * np.sin(2 * phi), "upperneck.ry": 1.5 * np.sin(phi), "upperneck.rz": 0.5 * np.cos(phi),
        "head.rx": 3.0 + 1.2 * np.sin(2 * phi + 1.0), "head.ry": 1.0 * np.sin(phi), "head.rz": 0.8 * np.cos(phi),
    }
    ch.update(_limb(phi, a, "l"))
    ch.update(_limb(phi, a, "r"))
    frames = np.stack([ch[c] for c in CMU_CHANNELS], axis=1)
    # AR(1) jitter so no two cycles are identical, as in real capture
    noise = np.zeros_like(frames)
    e = rng.normal(0, 0.25, frames.shape)
    for k in range(1, T):
        noise[k] = 0.95 * noise[k - 1] + e[k]
    moving = np.array([not c.startswith(("root.t", "root.ry")) and "clavicle" not in c and "fingers" not in c
                       for c in CMU_CHANNELS])
    frames[:, moving] += noise[:, moving]
    return Motion(frames, list(CMU_CHANNELS), fps, None, f"synthetic-{style}-{seed}")


def trials(n: int, seconds: float = 6.0, seed: int = 0, fps: float = FPS) -> list[Motion]:
    """``n`` synthetic walks with seeds ``seed .. seed + n - 1``."""
    return [gait(seconds, seed + i, fps) for i in range(n)]
