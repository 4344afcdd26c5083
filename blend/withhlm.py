"""``default-hlm``: ``default`` and the HLM's online filter side by side, weighed per joint group.

Both experts run on every frame of a stream, composed through the public Model interface only
(``stream`` / ``step`` / ``step_batch`` / ``Fill.std``): ``default`` (blend.model: hold, damped
velocity, a conditional Gaussian) and ``hlm`` (hlm.model: the locomotion model's forward filter,
trained on the locomotion takes).  For a channel j of group g missing for k frames, with D and H
the experts' fills and sd_D, sd_H their stds:

    fill = D + w wrap(H' - D),      w = W[g, bin(k), bin(q)] in [0, 1]
    H'   = H + o a^(k - 1),         o = wrap(D - H) on the gap's first frame, a = exp(-1 / tau)

so the HLM's part starts the gap where ``default`` does (where the performer was: the HLM's own
first filled frame is off by a median 2.85 deg) and comes to its own cycle over ``tau`` frames
(ANCHOR_TAU, chosen on VALIDATION with W).

``q`` is the stream's evidence that the HLM understands this motion, learnt online from what is
still observed (a *shadow check*): while at most ``SHADOW_MAX_MISS`` channels are really missing,
one observed limb group at a time is hidden from the HLM (never from ``default``, never from the
output: the caller gets the observed values) for ``SHADOW_LEN`` frames, then ``SHADOW_PAUSE``
frames rest, groups in turn.  Over a window the HLM's squared error on the hidden group is
compared with holding the group's value from the window's start: r = e_HLM / e_hold, and
log q = the decayed mean of log r over windows (``Q_DECAY`` per window, one prior window of
log q = 0).  A walk the HLM knows gives q well below 1; basketball gives q above 1, where the
fitted W is 0 and the fill is ``default``'s own.

W is fitted on VALIDATION only (bench/default_hlm_tune.py: the gaps protocol's bursts with seeds
100-102 and pan2009's pattern, on the experts trained on TRAIN): per cell the least-squares
weight of (H - D) against (truth - D), clipped to [0, 1], in two folds by take, and the smaller
of the two kept (a cell the two halves disagree on leans to ``default``).  Root translation
(``root-pos``) is never taken from the HLM: its root position drifts over long gaps (1.1-1.4 m
with the root erased), so W[root-pos] = 0 and the fill there is ``default``'s hold/velocity.

std: the experts as a two-part mixture, var = (1 - w) sd_D^2 + w sd_H^2 + w (1 - w) wrap(H - D)^2,
times a scale S[g, bin(k)] fitted on VALIDATION so that 2 std hold 95% of the errors there.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from lacuna import modelfile
from lacuna.filler import Fill, FillerError, FillerState, Model, check_frame
from mocap.representation import is_angle
from mocap.rootrot import wrap180 as wrap

METHOD = "default-hlm"
SHIPPED = Path(__file__).with_name("withhlm.json")
GROUP_NAMES = ("root", "torso", "head-neck", "left-arm", "right-arm", "left-leg", "right-leg", "other", "root-pos")
SHADOW_GROUPS = (1, 2, 3, 4, 5, 6)     # the limb groups a shadow window may hide (never the root)
ROOT_POS = 8
T_EDGES = np.array([1.5, 6, 12, 30, 60, 120, 240])   # frames since onset (at 120 Hz: 1, 50, 100, 250 ms, 0.5, 1, 2 s)
Q_EDGES = np.log(np.array([0.35, 0.6, 1.0]))          # log q bins
SHADOW_LEN = 60
SHADOW_PAUSE = 30
SHADOW_MAX_MISS = 12
Q_DECAY = 0.85
ANCHOR_TAU = 30.0   # frames; replaced by the shipped choice (withhlm.json)


def group_index(channels: list[str]) -> np.ndarray:
    """The joint group of each channel, as blend.model groups them (its 9 groups, same order)."""
    from blend.model import GROUP_NAMES as BG
    from blend.model import group_of

    if tuple(BG) != GROUP_NAMES:
        raise RuntimeError(f"blend.model's groups {BG} are not the ones {METHOD}'s weights are fitted on")
    return np.array([group_of(c) for c in channels], np.int64)


def t_bin(k: np.ndarray) -> np.ndarray:
    return np.searchsorted(T_EDGES, k, side="right")


def q_bin(logq: float) -> int:
    return int(np.searchsorted(Q_EDGES, logq, side="right"))


def shipped() -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(W (G, T, Q), S (G, T), what was chosen) from blend/withhlm.json; zeros (= ``default``) and
    ones before tuning."""
    G, TB, QB = len(GROUP_NAMES), len(T_EDGES) + 1, len(Q_EDGES) + 1
    if not SHIPPED.exists():
        return np.zeros((G, TB, QB)), np.ones((G, TB)), {}
    d = json.loads(SHIPPED.read_text())
    W, S = np.array(d["W"], float), np.array(d["S"], float)
    if W.shape != (G, TB, QB) or S.shape != (G, TB):
        raise ValueError(f"{SHIPPED}: W {W.shape} / S {S.shape} do not match ({G}, {TB}, {QB}) / ({G}, {TB})")
    return W, S, d.get("chosen", {})


class WithHLMModel(Model):
    """``default`` and ``hlm`` on the same channels, stacked by W and S (module doc)."""

    method = METHOD
    causal = True

    def __init__(self, default: Model, hlm: Model, W: np.ndarray, S: np.ndarray, meta: dict[str, Any] | None = None,
                 tau: float = ANCHOR_TAU):
        if list(default.channels) != list(hlm.channels):
            raise FillerError(f"{METHOD}: the experts' channels differ ({len(default.channels)} vs {len(hlm.channels)})")
        self.default, self.hlm = default, hlm
        self.channels = list(default.channels)
        self.group = group_index(self.channels)
        self.ang = np.array([is_angle(c) for c in self.channels])
        W = np.clip(np.asarray(W, float), 0.0, 1.0).copy()
        W[ROOT_POS] = 0.0    # root translation: hold/velocity only (module doc)
        self.W, self.S = W, np.asarray(S, float)
        self.tau = float(tau)
        self.anchor = float(np.exp(-1.0 / self.tau)) if self.tau > 0 else 0.0
        self.meta = dict(meta or {})
        self._cols = [np.flatnonzero(self.group == g) for g in SHADOW_GROUPS]

    def stream(self) -> WithHLMState:
        return WithHLMState(self)

    def step_batch(self, states, frames, observed, level=None):
        mine = all(isinstance(s, WithHLMState) and s.m is self for s in states)
        if not mine or not states:
            return super().step_batch(states, frames, observed, level)
        F = np.asarray(frames, np.float64)
        O = np.asarray(observed, bool)
        if F.shape != (len(states), self.n_channels) or O.shape != F.shape:
            raise FillerError(f"a batch of {len(states)} streams needs frames and masks of shape "
                              f"({len(states)}, {self.n_channels}) (got {F.shape} and {O.shape})")
        if (O & ~np.isfinite(F)).any():
            i, j = np.argwhere(O & ~np.isfinite(F))[0]
            raise FillerError(f"observed values must be finite (got NaN/inf in stream {i} at channel {j})")
        HO = np.stack([s._hlm_mask(O[i]) for i, s in enumerate(states)])
        dfills = self.default.step_batch([s.ds for s in states], F, O)
        hfills = self.hlm.step_batch([s.hs for s in states], F, HO)
        return [s._combine(F[i], O[i], dfills[i], hfills[i]) for i, s in enumerate(states)]

    def info(self) -> dict[str, Any]:
        return {**super().info(), "experts": [self.default.method, self.hlm.method]}

    # ---- persistence: both experts' arrays in one file, prefixed d/ and h/ ------------------------
    def save(self, path: str) -> None:
        parts: dict[str, Any] = {}
        arrays: dict[str, np.ndarray] = {"W": self.W, "S": self.S}
        with tempfile.TemporaryDirectory() as tmp:
            for key, m in (("d", self.default), ("h", self.hlm)):
                p = str(Path(tmp) / f"{key}.npz")
                m.save(p)
                meta, arr = modelfile.load_arrays(p)
                parts[key] = meta
                arrays.update({f"{key}/{k}": v for k, v in arr.items()})
        meta = {**self.meta, "method": METHOD, "channels": self.channels, "experts": parts, "tau": self.tau,
                "bins": {"t_edges": T_EDGES.tolist(), "q_edges": Q_EDGES.tolist()}}
        modelfile.save_arrays(path, meta, arrays)

    @classmethod
    def load(cls, path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> WithHLMModel:
        parts = meta.get("experts")
        if not isinstance(parts, dict) or set(parts) != {"d", "h"}:
            raise modelfile.ModelFileError(f"{path}: {METHOD} model without its two experts' metadata")
        if parts["d"].get("method") != "default" or parts["h"].get("method") != "hlm":
            raise modelfile.ModelFileError(f"{path}: {METHOD} experts must be default and hlm "
                                           f"(got {parts['d'].get('method')}, {parts['h'].get('method')})")
        from blend.model import DefaultModel
        from hlm.model import load as load_hlm

        sub = {key: {k[2:]: v for k, v in arrays.items() if k.startswith(key + "/")} for key in ("d", "h")}
        d = DefaultModel.load(path, parts["d"], sub["d"])
        h = load_hlm(path, parts["h"], sub["h"])
        G, TB, QB = len(GROUP_NAMES), len(T_EDGES) + 1, len(Q_EDGES) + 1
        W = modelfile.require(path, arrays, "W", (G, TB, QB))
        S = modelfile.require(path, arrays, "S", (G, TB))
        if list(meta["channels"]) != list(d.channels):
            raise modelfile.ModelFileError(f"{path}: channel list does not match its experts'")
        tau = meta.get("tau", ANCHOR_TAU)
        if not isinstance(tau, int | float) or tau < 0:
            raise modelfile.ModelFileError(f"{path}: {METHOD} 'tau' must be a number >= 0 (got {tau!r})")
        return cls(d, h, W, S, {k: v for k, v in meta.items() if k not in ("experts", "bins", "channels", "method", "tau")},
                   float(tau))


class WithHLMState(FillerState):
    """One stream: each expert's own state, frames since onset, and the shadow check."""

    def __init__(self, model: WithHLMModel):
        self.m = model
        C = model.n_channels
        self.ds = model.default.stream()
        self.hs = model.hlm.stream()
        self.k = np.zeros(C, np.int64)
        self.o = np.zeros(C)         # the HLM's anchoring offset (module doc)
        self.logq_sum, self.logq_n = 0.0, 1.0   # one prior window at log q = 0
        self.sh = -1                 # index into SHADOW_GROUPS of the hidden group, -1: none
        self.sh_n = 0                # frames into the window (or, with sh = -1, the pause left)
        self.sh_next = 0             # the next group to hide
        self.sh_hold = np.zeros(C)   # last observed values (the window's hold baseline)
        self.eh = self.e0 = 0.0
        self.collect = False         # bench/default_hlm_tune.py reads ``comp`` after each step
        self.comp: dict[str, np.ndarray] | None = None

    @property
    def logq(self) -> float:
        return self.logq_sum / self.logq_n

    def _close(self) -> None:
        if self.sh_n >= SHADOW_LEN // 3 and self.e0 > 0:
            r = np.log(max(self.eh, 1e-9) / max(self.e0, 1e-9))
            self.logq_sum = Q_DECAY * self.logq_sum + float(np.clip(r, -4.0, 4.0))
            self.logq_n = Q_DECAY * self.logq_n + 1.0
        self.sh, self.sh_n, self.eh, self.e0 = -1, SHADOW_PAUSE, 0.0, 0.0

    def _hlm_mask(self, obs: np.ndarray) -> np.ndarray:
        """The HLM's mask this frame: ``obs`` with the shadow group hidden (opens/closes windows)."""
        m = self.m
        busy = int((~obs & (m.group != ROOT_POS)).sum()) > SHADOW_MAX_MISS
        if self.sh >= 0:
            cols = m._cols[self.sh]
            if busy or not obs[cols].all() or self.sh_n >= SHADOW_LEN:
                self._close()
        elif self.sh_n > 0:
            self.sh_n -= 1
        elif not busy:
            for i in range(len(SHADOW_GROUPS)):
                g = (self.sh_next + i) % len(SHADOW_GROUPS)
                cols = m._cols[g]
                if len(cols) and obs[cols].all():
                    self.sh, self.sh_n, self.sh_next = g, 0, (g + 1) % len(SHADOW_GROUPS)
                    break
        if self.sh < 0:
            return obs
        ho = obs.copy()
        ho[m._cols[self.sh]] = False
        return ho

    def step(self, frame, observed=None) -> Fill:
        f, obs = check_frame(frame, observed, self.m.n_channels)
        ho = self._hlm_mask(obs)
        return self._combine(f, obs, self.ds.step(f, obs), self.hs.step(f, ho))

    def _combine(self, f: np.ndarray, obs: np.ndarray, d: Fill, h: Fill) -> Fill:
        m = self.m
        if self.sh >= 0:
            cols = m._cols[self.sh]
            a = cols[m.ang[cols]]
            self.eh += float(np.sum(wrap(h.frame[a] - f[a]) ** 2))
            self.e0 += float(np.sum(wrap(self.sh_hold[a] - f[a]) ** 2))
            self.sh_n += 1
        else:
            self.sh_hold = np.where(obs, f, self.sh_hold)
        self.k = np.where(obs, 0, self.k + 1)
        miss = ~obs
        out = np.where(obs, f, d.frame)
        std = np.zeros(m.n_channels)
        if miss.any():
            j = np.flatnonzero(miss)
            g, tb = m.group[j], t_bin(self.k[j])
            w = m.W[g, tb, q_bin(self.logq)]
            D, H = d.frame[j], h.frame[j]
            raw = np.where(m.ang[j], wrap(H - D), H - D)
            first = self.k[j] == 1
            self.o[j[first]] = -raw[first]
            off = self.o[j] * m.anchor ** (self.k[j] - 1) if m.tau > 0 else 0.0
            diff = raw + off
            out[j] = D + w * diff
            var = (1 - w) * d.std[j] ** 2 + w * h.std[j] ** 2 + w * (1 - w) * diff ** 2
            std[j] = m.S[g, tb] * np.sqrt(var)
            if self.collect:
                self.comp = {"idx": j, "k": self.k[j].copy(), "D": D.copy(), "H": D + raw, "o": self.o[j].copy(), "sD": d.std[j].copy(),
                             "sH": h.std[j].copy(), "logq": np.full(len(j), self.logq)}
        elif self.collect:
            self.comp = None
        return Fill(out, std, miss, {**h.extras, "hlm_q": float(np.exp(self.logq))})


LOCOMOTION = ("walk", "turn", "run")


def train_model(training_set: Any, W: np.ndarray | None = None, S: np.ndarray | None = None,
                **options: Any) -> WithHLMModel:
    """``default`` on every take of ``training_set``; the HLM on its locomotion takes (labels walk,
    turn, run; every take where it has no labels); W and S the shipped ones unless given."""
    import time

    from blend.train import train_model as train_default
    from hlm.methods import train_model as train_hlm

    t0 = time.perf_counter()
    seqs, ch, names = training_set.sequences, training_set.channels, list(training_set.names)
    labels = list(getattr(training_set, "labels", []) or [])
    loco = [i for i, lab in enumerate(labels) if lab in LOCOMOTION] if labels else list(range(len(seqs)))
    if not loco:
        raise FillerError(f"{METHOD}: no locomotion take among the {len(seqs)} training takes to train the HLM on")
    d = train_default(seqs, ch, names, fps=options.get("fps") or getattr(training_set, "fps", None))
    hopts = {k: v for k, v in options.items() if k not in ("fps",)}
    h = train_hlm([seqs[i] for i in loco], ch, [names[i] for i in loco], **hopts)
    W0, S0, chosen = shipped()
    tau = float(chosen.get("tau", ANCHOR_TAU))
    meta = {"training": {"default": names, "hlm": [names[i] for i in loco],
                         "seconds": round(time.perf_counter() - t0, 2)},
            "weights": {"shipped": SHIPPED.name, **chosen} if W is None else {"given": True}}
    return WithHLMModel(d, h, W0 if W is None else W, S0 if S is None else S, meta, tau)
