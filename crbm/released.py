"""Training settings of the faithful ``crbm`` and of the paper's text, as plain data (imported by
the CLI at start-up, so nothing heavy here)."""

# How Taylor's released training code (mixgaussiancrbm.m of github:gwtaylor/imCRBM, run with one
# component as /work/shared/anchors/taylor-octave does) trains, where the CRBM class's own
# defaults follow the paper's text (section 3) instead: each past frame that conditions a training
# case gets N(0, 1) noise; hidden probabilities, not samples, in the data term of eqs. 4 and 6;
# biases initialised from N(0, 0.01^2) like the weights; mini-batches cut once; single precision
# (train.m: ``batchdata = single(Z)``, mixgaussiancrbm.m: ``single(...)`` throughout).  The faithful
# ``crbm`` trains this way (docs/BENCHMARKS.md, "CRBM against the released code").
RELEASED = {"history_noise": 1.0, "positive_hidden": "prob", "bias_init_std": 0.01, "batches": "fixed",
            "dtype": "float32"}
# what ``crbm`` trained with before 2026-12-01 (the paper's text, fresh mini-batches every epoch);
# ``crbm-imp`` and ``crbm-ens`` keep it
PAPER_TEXT = {"history_noise": 0.0, "positive_hidden": "sample", "bias_init_std": 0.0, "batches": "reshuffle",
              "dtype": "float64"}
# The released code's input (the anchor's train.m, which produced the figures issue 17 quotes):
# the raw channels of cmu35WalkJog.mat, root position and Euler angles as captured, z-scored
# (``Z = (Y(:,keep) - mu(keep)) ./ sd(keep)``, no unwrapping: rhand.rz, whose values cross
# +-180 deg, stays as captured).  ``crbm`` models them so (representation root_mode "raw",
# unwrap False).  The improved variants keep the paper's body-centred root (section 4) and
# angles unwrapped about their circular mean.
RELEASED_INPUT = {"root_mode": "raw", "unwrap": False}
