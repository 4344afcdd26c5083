"""Registers the CRBM methods with ``lacuna.registry`` and the model-file loader.

* ``crbm``         the paper, faithfully, trained as Taylor's released code trains (CD-1 of
                   section 3 with N(0, 1) noise on the conditioning history, hidden probabilities
                   in the data term, biases from N(0, 0.01^2), fixed mini-batches, single
                   precision) on its input (the raw channels z-scored: root not body-centred,
                   angles as captured, not unwrapped), fill by K = 30
                   clamped Gibbs iterations plus a final mean-field step, one chain (section 5).
* ``crbm-mf``      deterministic mean-field fill (hidden probabilities, no noise) of a CRBM
                   trained as the paper's text says (section 3: sampled hiddens in the data term,
                   clean history).
* ``crbm-2level``  a second CRBM on the first level's hidden activities (section 6), filled by
                   Gibbs over both levels; both levels trained as the paper's text says.
* ``crbm-imp``     improvements: hidden probabilities in the data term of CD-1 (as the released
                   code does), parameters averaged over the last 20% of epochs, S = 8
                   chains averaged in the fill, and per-stream bias adaptation (bias_rate 0.02,
                   ``crbm.filler``).
* ``crbm-ens``     three ``crbm-imp`` CRBMs from different seeds filling together: every frame
                   each member runs its chains from the shared history and the fill is the mean
                   of all chains (``crbm.ensemble``); removes most of the training-seed spread.
"""
from __future__ import annotations

from typing import Any

from crbm.persist import METHODS, load_model_arrays
from crbm.released import PAPER_TEXT, RELEASED_INPUT
from crbm.train import train_model
from lacuna.modelfile import register_loader
from lacuna.registry import MethodSpec, register_method

# option name -> keyword of train_model; anything else a protocol passes is ignored
_OPTIONS = ("hidden", "members", "order", "epochs", "seed", "history_noise", "positive_hidden", "bias_init_std",
            "batches", "average_last", "levels",
            "level2_hidden", "level2_epochs", "n_gibbs", "n_chains", "mode", "bias_rate", "fps", "progress",
            "progress_every", "root_mode", "unwrap", "dtype", "final_step")

VARIANTS: dict[str, dict[str, Any]] = {
    # the released code's input (raw root channels, crbm.released.RELEASED_INPUT) and training
    # (train_model's defaults = crbm.released.RELEASED)
    "crbm": dict(RELEASED_INPUT),
    # trained and filled as ``crbm`` was before 2026-12-01 (the paper's text), as their figures
    # in docs/BENCHMARKS.md ## CRBM were measured; with the released code's training the
    # mean-field fill's 35_29 upper body was 14.2 (training seed 1) against 12.8 (seed 0) before
    "crbm-mf": {**PAPER_TEXT, "mode": "mean-field", "final_step": "input"},
    "crbm-2level": {**PAPER_TEXT, "levels": 2, "final_step": "input"},
    # the improved variants keep the training they were tuned with (clean history, zero biases,
    # fresh mini-batches every epoch), with the released code's hidden probabilities, and the
    # fill's final step as they were measured (crbm.filler.FINAL_STEPS)
    "crbm-imp": {**PAPER_TEXT, "positive_hidden": "prob", "average_last": 0.2, "n_chains": 8, "bias_rate": 0.02,
                 "final_step": "input"},
    "crbm-ens": {**PAPER_TEXT, "positive_hidden": "prob", "average_last": 0.2, "members": 3, "n_chains": 4,
                 "bias_rate": 0.02, "final_step": "input"},
}


def _trainer(name: str):
    def train(training_set: Any, **options: Any):
        kw = {**VARIANTS[name], **{k: v for k, v in options.items() if k in _OPTIONS and v is not None}}
        kw.setdefault("progress", True)       # a progress line on stderr every 200 epochs
        kw.setdefault("progress_every", 200)
        return train_model(training_set.sequences, training_set.channels, names=list(getattr(training_set, "names", []) or []),
                           method=name, **kw)

    return train


def _describe(name: str) -> str:
    """The method's bullet from this module's docstring, on one line."""
    doc = __doc__ or ""
    part = doc.split(f"``{name}``", 1)[1].split("\n* ")[0]
    return " ".join(part.split())


for _name in METHODS:
    register_method(MethodSpec(_name, _trainer(_name), description=_describe(_name), causal=True,
                               defaults=dict(VARIANTS[_name])))
    register_loader(_name, load_model_arrays)
