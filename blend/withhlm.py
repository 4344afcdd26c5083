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
frames rest, groups in turn.  A second ``default`` stream (the *twin*: at each window's opening a
copy of the stream's own ``default`` state, stepped only while the window lasts) sees the same
hidden group.  Over a window, from its ``SHADOW_SKIP``-th frame on (the check judges the HLM on
the horizons it is trusted with: over a window's first frames the twin is barely off the last value
and the HLM's own start is what the mixing's anchoring removes), the HLM's squared error on the
hidden angles is compared with the twin's: r = e_HLM / e_default.  The main ``default`` stream never
sees the shadow mask.

The rule the check enforces (safe where evidence is thin): **the HLM gets a share only on evidence
that it predicts this stream better than the blend, and only as much as a pessimistic bound on that
evidence allows.**  The q bin is chosen by an upper confidence bound on log q, not its mean:

    log q+ = m + Q_Z sqrt(v / n),   m, n: decayed (Q_DECAY per window) mean and count of log r, with
                                   Q_PRIOR_N pseudo-windows at log r = Q_PRIOR_AT = log 1.1 ("the HLM is
                                   not clearly better")
                                   in both, v = (Q_V0 + decayed sum of (log r - m)^2) / (1 + n)
    log q+ >= log r of the window just closed, where r > SHADOW_REVOKE (and > 1.1): one window that
    finds the HLM worse takes its share away at once, however well it did before (the motion changed)

and before any window has been scored log q+ = LOGQ_UNSCORED, the last bin, where W = 0 whatever
the fit says (as for q+ > 1.1).  So a stream starts as ``default`` alone (the blend with its guard,
which is itself kept within hold by its own check), an HLM that is wrong from the first frame never
gets a share (tests/test_default_hlm.py: within 1% of the blend on every gap, the first included),
and the share grows as windows agree (n up, the bound down), falls back when one disagrees (v up).
The old policy (one prior window at q = 1, the bin 0.7-1.1 with its validation-fitted share from the
first frame) let the HLM in before it had been judged: TEST's 49_20 was 3% worse than hold.
The prior and the revocation (bench/notebook/robust-5.md): on VALIDATION stress streams (many
stream starts on non-locomotion, a walk spliced before a non-locomotion take) one early window on
one group judged the HLM better by chance (n = 1 gave q+ under 1.1), and after a walk the decayed
mean of the good windows kept the HLM's share for seconds of basketball (3.2x the blend alone on
35_28 + 49_19).  The constructed test: an HLM right for 600 frames, then 20-30 deg off, loses its
share at the first window that sees it (tests/test_default_hlm.py).
The prior's window sits at the share's cut, log 1.1, not at 0 (bench/notebook/loao-41.md): with TRAIN's
non-walk activities each held out of its own model, one window where the HLM's error was ~25% under the
blend's gave it most of a take it had never seen (13_39's jumps 11.63 deg against hold's 13.24, 49_18
6.44 against 2.81); now such a window alone leaves the bound above the cut, a window at half the blend's
error or a second such window gives a share (VALIDATION's walks pay 2.6%).
The check also runs while up to SHADOW_MAX_MISS channels are really missing (longer dropouts are
when it matters), never on a group with a missing channel.  Every constant of the check (Q_Z,
SHADOW_SKIP, SHADOW_MAX_MISS, SHADOW_WARM, SHADOW_EAGER, Q_PRIOR_N, SHADOW_REVOKE) was chosen on
VALIDATION with W and S refitted for each (bench/default_hlm_tune.py --z/--skip/--max-miss/--warm/
--eager/--prior/--revoke, the last two with --stress: bench/default_stress.py; the choice is
recorded in blend/withhlm.json "policy"; bench/notebook/mixq-4.md).

W is fitted on VALIDATION only (bench/default_hlm_tune.py: the gaps protocol's bursts with seeds
100-102 and pan2009's pattern, on the experts trained on TRAIN): per cell the least-squares
weight of (H - D) against (truth - D), clipped to [0, W_MAX], in two folds by take, and the smaller
of the two kept (a cell the two halves disagree on leans to ``default``).  Root translation
(``root-pos``) is never taken from the HLM: its root position drifts over long gaps (1.1-1.4 m
with the root erased), so W[root-pos] = 0 and the fill there is ``default``'s hold/velocity.

std: the experts as a two-part mixture, var = (1 - w) sd_D^2 + w sd_H^2 + w (1 - w) wrap(H - D)^2,
times a scale S[g, bin(k)] fitted on VALIDATION so that 2 std hold 95% of the errors there in the
activity that needs the widest band (walk, turn, run, non-locomotion: each then holds >= 95%),
then times a per channel x time-bin factor F (blend/calib.py, fitted on VALIDATION; 1 in files
written before it): folded into the compiled mixing's per-channel S table, one factor on the numpy
path's std; fills unchanged.

Smooth (``set_smooth``; the ``smooth`` table of a model file).  The mixing is piecewise constant
in its cells: a fill inside a gap jumped where the time bin or the q bin changed (w moves by up to
0.6 at once), where the HLM's phase jumped (VALIDATION's walking_21: phase 0.137 -> 0.187 in one
frame, a 14-degree pop) and where the blend re-anchored as other channels came and went.  The
*pop limit*: from a gap's third frame on, the fill y = D + w wrap(H' - D) may depart from its own
linear course (last value plus last step, y[t-1] + s, s the step the course took) by at most

    POP + POP_REL |s|   degrees a frame,

the excess x going into an offset e (e <- e exp(-1 / POP_TAU) - x; the course itself follows y, not
the limited output) so what was held back comes in over a few frames: fill = y + e.  The first two
frames of a gap set the course and are never limited.  A fill that moves smoothly, however fast, is
never touched.  POP = 2, POP_REL = 1, POP_TAU = 3 were chosen on VALIDATION (bench/default_smooth.py,
the gaps protocol's seeds 0-2; the rule, set before the last round: every activity's RMS within
1.5% and every gap-length bin within 3% of no smoothing, then the lowest pooled RMS, fewer pops to
break ties; bench/notebook/smooth-6.md): pops above 2 degrees (mocap/metrics.py: a frame's step
beyond the truth's own) 0.53% -> 0.31% of values, the largest 38 -> 11 degrees, pooled RMS -0.1%
(walks -1.3%, runs +0.8%: a run's jumps are partly corrections).  The *knots* (T_KNOTS: W and S
read linearly between the bins' centres) are kept as an option, off: they cost the VALIDATION
run's short gaps 4.7%.  The *std knots* (S alone between the knots, ``std_knots``: the 2-std band
no longer steps at the bin edges; fills unchanged) are on: chosen on VALIDATION by the calibration
rule (every activity's share within 2 std in 0.90-0.98, then the pooled NLL): NLL 2.2122 -> 2.1987,
within 2 std 0.9622 -> 0.9628 (the run's 0.9051 -> 0.9007, the lowest).  Files written before
smoothing load with all of it off and fill as they did.  The *band's share* (``band_tau``): the
std's mixture uses w low-passed over BAND_TAU = 12 frames from a gap's second frame on, so where w
steps (a time bin's edge, a q bin's change mid-gap) the band bends over ~0.1 s instead of stepping;
the fill keeps its w.  Chosen on VALIDATION (bench/notebook/band-8.md): the band's kinks (a second
difference above 10% of the std) 2.4% -> 1.6% of erased values (walks 7.0% -> 3.2%), fills unchanged,
within 2 std 0.9627 -> 0.9627, NLL 2.1977 -> 2.1992.  Files whose smooth table has no band_tau load
with it off.

Rate (``rate_a`` in the smooth table, ``rate_ref`` in the model file; off: a = 0).  Per stream and
channel, decayed sums (exp(-1 / RATE_TAU) a frame, RATE_TAU = 120) of |dx| (wrapped for angles) and of
1 over consecutive observed frames; a missing channel keeps the rate of its last observed frames, and
its std is times clip((rate / ref)^a, RATE_LO, RATE_HI), ref the TRAIN data's mean |dx| a frame of that
channel (``rate_ref``, computed by train_model; files without it load with the rate off), 1 with under
one value's weight of history.  Fills unchanged; numpy and compiled mixing equal
(tests/test_default_band_rate.py).  Tried for issue 17 (walks' band too wide) and not chosen
(bench/notebook/band-12.md): on VALIDATION gaps seeds 0-2 / 3-4, a = 0.5 moves within 2 std walk
0.990 -> 0.990 / 0.988 -> 0.986, turn 0.959 -> 0.922 / 0.959 -> 0.929, run 0.906 -> 0.964 /
0.968 -> 0.986, non-locomotion 0.954 -> 0.918 / 0.947 -> 0.903, NLL +11% / +17%; with S refitted by
its own rule the walks widen (0.994 / 0.992).  A walk moves at the training data's typical rate
(median rate / ref 0.94), turns and non-locomotion at 0.4x, a run at 2.2x: the rate tells a run from a
walk but cannot narrow the walks.

Band q (``band_q`` (G, Q) and ``band_gate`` (r0, r1) in the model file, from withhlm.json's "band_q";
off: ones; files without them load with ones).  Where the HLM is clearly better (q bins 0, 1) only walks
were left to set S, and their band was too wide (issue 17).  A missing channel of group g in q bin q has
its std times mb, the low-passed (over band_tau, from the gap's first frame, as the band's share)
1 + (band_q[g, q] - 1) gate, gate from the *stream's* rate R = the median over angle channels with a
reference and one value's weight of history of rate / ref ("Rate"'s estimate, read before the frame's
update): 1 for R <= r0, 0 for R >= r1, linear between, 0 without a rate.  So the narrowing, fitted on the
walks, holds only at walking pace: band-10 (bench/notebook/band-10.md) had it ungated, and TEST's run
35_25, which reaches q < 0.7, fell to 0.84 within 2 std.  Fitted on VALIDATION gaps seeds 100-102
(bench/default_band_q.py: band_q by S's own rule per (group, q0/q1); r0 = the walks' 90% quantile of R,
1.63, r1 = the run's 10% quantile, 1.77), chosen by bench/notebook/band-13.md's rule on VALIDATION seeds
0-2 / 3-4: within 2 std walk 0.990 -> 0.976 / 0.988 -> 0.977 (into [0.90, 0.98]), turn, run and
non-locomotion unchanged, NLL 2.199 -> 2.179 / 2.212 -> 2.170; then TEST seeds 0-4, after the choice:
walk 0.967 -> 0.961, run 0.943 -> 0.942 (ungated: 0.861), turn and non-locomotion unchanged, NLL
2.187 -> 2.186.  Fills unchanged; numpy and compiled mixing equal (tests/test_default_band_q.py); its
compiled kernel ``q_band`` runs after ``mix_row`` only where band_q is on (off: main's mix_row).

Pace (``pace_tau``, ``pace_k``, ``pace_a`` in the smooth table; off: pace_tau 0; files without them load
with it off; off too without ``rate_ref``).  For issue 17's stops (robust-10: a performer holds a limb
still inside a gap while the fill moves it): per stream, every channel's decayed sums over consecutive
observed frames of |dx| and of 1, fast (exp(-1 / pace_tau)) and slow (RATE_TAU); R = the median over the
angle channels observed now of fast rate / rate_ref; on a gap's first frame a missing channel keeps r0,
the same median of the slow rate.  The fill y (the mixing's output) then moves only its own step times
s = clip(R / ref, 0, 1), ref = pace_k r0 (or min(pace_k r0, pace_a) where pace_a > 0):
z[t] = z[t-1] + s wrap(y[t] - y[t-1]), from the last observed value (no pop); s = 1 where a rate is
undefined; std unchanged.  Numpy ``_pace`` and compiled ``pace_row`` equal (tests/test_default_pace.py).
Tried and not chosen (bench/notebook/pace-11.md): on VALIDATION, pace_k 1 finds the stops (stress gaps
above hold 14 -> 9, 49_19 4.87 -> 4.49 against hold 4.53) but slows the walks, whose fast rate swings
within a stride (walk rms +10-23%); pace_k 0.5 and the stillness level pace_a (0.15, 0.25) spare the
walks and find no stop: where 49_19 is above hold the observed body keeps moving (0.35-0.67 x rate_ref).

Long erasures (``long_trust`` (K, QMAX) in the model file's metadata; files without it: off).  The
shadow check judges the HLM on a hidden limb over 0.5 s windows, and only while <= SHADOW_MAX_MISS
channels are missing: with the whole upper body erased (pan2009's pattern) no window runs and q+
stays where the few windows before left it, and against a twin that is barely off the last value
over 0.5 s, a walk's HLM can read q+ just above 1.1 (VALIDATION 35_28: 1.19, from 2 windows) and
yield for seconds over which ``default`` decays to its hold (35_28: default 11.69 deg^2 against
the HLM alone's 3.38).  So a channel outside the legs and the root position, missing for >= K frames
while every leg channel is observed (the legs then lock the HLM's gait phase: on pan2009's walks its
arm fill correlates 0.85-0.96 with the truth at lag 0-4 frames, bench/notebook/pan-11.md) and the
stream's q+ <= QMAX, mixes with the share W of the q bin 0.7-1.1 instead of the last bin's 0
(an extra q column of the compiled tables, index len(Q_EDGES) + 1; band_q's there is the last bin's).
K = 120, QMAX = 1.5 was chosen on pan2009 VALIDATION (K in {120, 240}, QMAX in {1.5, 3}) by pan-11's rule
and passed the gaps protocol's VALIDATION seeds 0-2 (pan2009 VALIDATION mean ratio to nn 0.464 -> 0.384,
35_28 11.69 -> 7.25 deg^2), but the VALIDATION stress of the check (bench/default_stress.py) shows the
gate opening on non-locomotion (49_19@110: 1.36x the blend alone) and TEST's non-locomotion agrees
(+1.2%): it is OFF by default (bench/notebook/pan-11.md); a model file with ``long_trust`` turns it on.
The *leg gate* (``long_gate`` (K, QL[, QR]) in the model file's metadata; files without it: off; an
alternative to ``long_trust``, not both) gathers its evidence in that regime: while more than
SHADOW_MAX_MISS channels are missing and every leg channel is observed, *long windows* hide one leg
(legs in turn, SHADOW_LEN frames, back to back) from a twin of the HLM (its state pool row copied at
the window's opening; the HLM the mixing uses keeps both legs) and from a twin of the blend, scored as
the check's windows into a per-stream q_long+ (the same bound; unscored again at each such erasure's
onset).  A channel outside the legs and the root position missing >= K frames, in a stream whose q+
is in the last bin, mixes with bin 0.7-1.1's W (the long column) while q_long+ <= QL (0: never); with
QR > 0, a scored q_long+ > QR sends the stream to the last bin (W = 0) whatever its q+ (the *revoke*).
Same fills on the numpy, compiled and block paths (the windows' planning, twins and scoring are one
Python routine, ``_long``, before the experts step; the mixing only reads the q bin it picks;
tests/test_default_long_gate.py).  Judged by bench/notebook/loco-12.md's rules (written before the runs)
and OFF by default (LONG_GATE): on pan2009 VALIDATION (60, 0.8) lifts 35_28 11.69 -> 4.91 deg^2 (mean
ratio to nn 0.464 -> 0.343), but under the same erasure on VALIDATION's basketball_4 it opens as well
(1.14x the fill without it; the gaps protocol and the stress bench never reach the regime); the revoke
(60, -, 1.1) brings the walk -> non-locomotion splices under such an erasure from up to 3.6x the blend
alone (10 of 12 above 1.1x) to within 0-20% of it, but revokes pan2009's walking_21 (3.49 -> 8.48).  Round 3
(the revoke alone at QR = SHADOW_REVOKE, the ordinary check's own bound, not a new fit) cut the pooled
non-walk regime MSE 27% with nothing else moving on VALIDATION, and failed on the same take (3.49 -> 6.50):
walking_21's first long window reads r = 2.5 on the hidden leg (a seated take reads 4.8-8.5), so no revoke
bound spares it without being fitted to those two takes.  A long window steps a second HLM and blend: the
stream's step costs ~2x in that regime (bench/loco12_stepcost.py), ~1.02x elsewhere; long_gate's fourth
value, ``rest`` (frames of rest after each long window, the first at the erasure's onset; 0: back to back;
SHADOW_PAUSE as the ordinary check's schedule), runs the twins on a third of that regime's frames.

long_ll (``long_ll`` (D, TAU) in the model file's metadata; files without it: off; bench/notebook/loco-13.md).
The evidence is the HLM's own, no twin: its forward step's normaliser, log p(z_t,o | z_<t,o) = log sum_s
pred(s) b_s(z_t,o) over the observed features (hlm.online.init_state's "ll", written by the numpy reference
and the compiled step alike), per observed feature.  In the regime above (more than SHADOW_MAX_MISS channels
missing, every leg channel observed) only the legs are observed, so it says how well the locomotion model
predicts the legs the performer still shows; a walker who stops (basketball, signals, sitting) is predicted
far worse than on the walk.  Per stream: a baseline (decayed mean over LL_BTAU frames of the level on frames
with <= SHADOW_MAX_MISS missing and q+ < 1.1, each frame at most LL_BCLIP below it; LL_BMIN frames of weight
needed), frozen at the erasure's onset; the erasure's level (decayed mean over TAU frames from its onset);
from LL_N0 frames into the erasure, a level more than D below the baseline revokes the share: the bound
to at least log SHADOW_REVOKE and the last q bin for the rest of the erasure (``_ll_track``, after the HLM's
step, before the q bin is read; the same Python on the numpy, compiled and block paths).  Chosen by
bench/notebook/loco-13.md's second look on VALIDATION (D in {2, 4, 8} x TAU in {30, 60}; round 1's bar, a
pooled drop of 25%, was above what the blend alone gives on its larger regime set): (4, 60) ships on
(LONG_LL): the regime set's pooled non-walk MSE 265 -> 213 deg^2 (the blend alone 210), no case worse, no
walk revoked, gaps / stress / pan2009 VALIDATION unchanged; ~1.02x the step outside the regime, ~1.08x in
it.  TEST, after the choice: -2.8% only, two splices 1.2x worse (the HLM was the better there) and walking_28's
splices untouched: its whole-body baseline (-28 nats a feature) is not comparable with the legs' level.
``long_ll_legs`` (a model-file key beside ``long_ll``; files without it: false, the above) puts the baseline
and the level on the same quantity: the HLM also keeps the normaliser over the observed leg features only
(hlm.online's "ll" columns 2-3, asked for through ``HLMModel.set_ll_feats``; the features whose every source
is a leg channel).  bench/notebook/loco-14.md: not eligible on VALIDATION (D in {2, 4, 8} at TAU = 60: the
pan2009-set model's walking_20 legs swing ~8 nats a feature within the walk, so D <= 4 revokes it (3.2x) and
D = 8 leaves 0.1 nat; D = 2 leaves < 2.5 nats on every walk; D >= 4 loses revokes the whole-body baseline
makes), so LONG_LL_LEGS = False; TEST (seen before the round), reported only: walking_28's splices revoked.
"""
from __future__ import annotations

import copy
import json
import math
import tempfile
from bisect import bisect_right
from pathlib import Path
from typing import Any

import numpy as np

from blend import calib
from blend.model import DefaultModel, checked_batch
from blend.withhlm_fast import RATE_FTZ, mix_row, observed_finite, pace_row, q_band, rate_band, shadow_counts
from lacuna import jit, modelfile
from lacuna.filler import BlockFill, Fill, FillerError, FillerState, Model, check_frame
from mocap.representation import is_angle
from mocap.rootrot import wrap180 as wrap

METHOD = "default-hlm"
SHIPPED = Path(__file__).with_name("withhlm.json")
GROUP_NAMES = ("root", "torso", "head-neck", "left-arm", "right-arm", "left-leg", "right-leg", "other", "root-pos")
SHADOW_GROUPS = (1, 2, 3, 4, 5, 6)     # the limb groups a shadow window may hide (never the root)
ROOT_POS = 8
T_EDGES = np.array([1.5, 6, 12, 30, 60, 120, 240])   # frames since onset (at 120 Hz: 1, 50, 100, 250 ms, 0.5, 1, 2 s)
Q_EDGES = np.log(np.array([0.4, 0.7, 1.1]))           # log q bins (chosen on VALIDATION among 4 sets)
SHADOW_LEN = 60
SHADOW_PAUSE = 120    # frames of rest between windows (chosen on VALIDATION among 30, 120, 240: bench/notebook/switch.md)
SHADOW_MAX_MISS = 24   # chosen on VALIDATION among 12, 24, 40, 99 (bench/default_hlm_tune.py)
SHADOW_SKIP = 30      # a window's first frames are not scored (module doc; chosen on VALIDATION among 0, 20, 30)
SHADOW_MIN = 10       # scored frames a window needs to count
SHADOW_WARM = 0       # frames of a stream before its first window (chosen on VALIDATION among 0, 30)
SHADOW_EAGER = 0      # windows back to back (no rest) until this many have counted (VALIDATION: 0, 2)
Q_DECAY = 0.85
Q_Z = 0.5             # how pessimistic the bound on log q is, in standard errors (chosen on VALIDATION among 0, 0.5, 1)
Q_V0 = 1.0            # the prior variance of a window's log r (one prior window's worth)
Q_PRIOR_AT = math.log(1.1)   # the log r of those pseudo-windows: "the HLM is not clearly better" (the share's cut; among 0, log 1.1, log 1.2 on activities held out of their model: bench/notebook/loao-41.md)
Q_PRIOR_N = 1.0       # pseudo-windows at log r = Q_PRIOR_AT in the bound (VALIDATION among 0, 1, 2: robust-5.md)
SHADOW_REVOKE = 1.5   # a window with r above this (and 1.1) sets the bound to at least its log r (VALIDATION among 0, 1, 1.5, 2, 4)
LOGQ_UNSCORED = math.log(100.0)   # no window scored yet: the bound is "no evidence", the last q bin (W = 0)
W_MAX = 0.95   # the HLM's share at most: its std is 0 on channels its training held still; default's keeps std > 0
ANCHOR_TAU = 30.0   # frames; replaced by the shipped choice (withhlm.json)
# Smoothing (module doc, "Smooth"): each time bin's knot, its centre in frames since onset (the first
# frame keeps bin 0; past the last knot, the last bin)
T_KNOTS = np.array([1.0, 3.5, 8.5, 20.5, 44.5, 89.5, 179.5, 360.0])
POP = 2.0        # degrees a frame the fill may depart from its own course, plus POP_REL x its last step (0: off)
POP_REL = 1.0
POP_TAU = 3.0    # frames: the decay of what the pop limit held back (all three chosen on VALIDATION: module doc)
BAND_TAU = 12.0  # frames: the band's share w low-passed over this (module doc; chosen on VALIDATION, band-8.md)
RATE_A = 0.0     # the band's rate exponent (module doc, "Rate"; 0: off)
LONG_TRUST_OFF = (0, 0.0)   # the long-erasure trust off (module doc, "Long erasures"): every model by default
LONG_TRUST = LONG_TRUST_OFF   # what models trained now carry; (120, 1.5) passed pan-11's rule but opens on non-locomotion
LEG_GROUPS = (5, 6)     # left-leg, right-leg: observed legs are what lock the HLM's gait phase
LEG_SHADOW = tuple(SHADOW_GROUPS.index(g) for g in LEG_GROUPS)   # their indices into SHADOW_GROUPS
LONG_GATE_OFF = (0, 0.0, 0.0, 0)   # the leg gate off (module doc, "Long erasures"): files without ``long_gate``
LONG_GATE = LONG_GATE_OFF   # what models trained now carry (bench/notebook/loco-12.md)
LONG_LL_OFF = (0.0, 0.0)    # the legs' predictive likelihood revoke off (module doc, "long_ll"): files without ``long_ll``
LONG_LL = (4.0, 60.0)       # what models trained now carry: chosen by bench/notebook/loco-13.md's second look
LONG_LL_LEGS = False        # long_ll's baseline and level on the legs' features only (``long_ll_legs``): not eligible, bench/notebook/loco-14.md
LL_N0 = 30          # frames of a long erasure before its level may revoke (= SHADOW_SKIP; fixed, not tuned)
LL_BTAU = 600.0     # frames: the decay of the baseline (5 s; fixed, not tuned)
LL_BMIN = 60.0      # the baseline's weight (decayed frames) it needs to count (fixed, not tuned)
LL_BCLIP = 1.0      # nats a feature: a frame enters the baseline at most this far below it (fixed, not tuned)
LOG_REVOKE = math.log(SHADOW_REVOKE)
LL_BDECAY = math.exp(-1.0 / LL_BTAU)
LOGQ_YIELD = float(Q_EDGES[-1])   # log 1.1: at or above it the HLM has no share (the last q bin)
RATE_TAU = 120.0   # frames: the decay of a channel's observed rate (1 s, about one walking cycle; fixed, not tuned)
RATE_LO, RATE_HI = 0.5, 2.0   # the rate's factor on the band is clipped to these (fixed, not tuned)
PACE_TAU = 0.0   # frames: the decay of the observed body's fast rate for the pace (module doc, "Pace"; 0: off)
PACE_K = 1.0     # the pace is 1 while the fast rate is at least PACE_K x the slow rate at the gap's onset
PACE_A = 0.0     # ... or at least this (x rate_ref; 0: no such level): the pace's reference is the smaller
NO_SMOOTH = {"knots": False, "std_knots": False, "pop": 0.0, "pop_tau": POP_TAU, "pop_rel": 0.0, "band_tau": 0.0,
             "rate_a": 0.0, "pace_tau": 0.0, "pace_k": PACE_K, "pace_a": PACE_A}   # files before smoothing
SMOOTH = {"knots": False, "std_knots": True, "pop": POP, "pop_tau": POP_TAU, "pop_rel": POP_REL, "band_tau": BAND_TAU,
          "rate_a": RATE_A, "pace_tau": PACE_TAU, "pace_k": PACE_K, "pace_a": PACE_A}   # the choice (withhlm.json's)
SMOOTH_SINCE = {"band_tau": 0.0, "rate_a": 0.0, "pace_tau": 0.0, "pace_k": PACE_K, "pace_a": PACE_A}   # keys a file's smooth table may lack (written before them): off


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
                 tau: float = ANCHOR_TAU, cal: np.ndarray | None = None, smooth: dict[str, Any] | None = None,
                 rate_ref: np.ndarray | None = None, band_q: np.ndarray | None = None,
                 band_gate: Any = None):
        if list(default.channels) != list(hlm.channels):
            raise FillerError(f"{METHOD}: the experts' channels differ ({len(default.channels)} vs {len(hlm.channels)})")
        self.default, self.hlm = default, hlm
        self.channels = list(default.channels)
        self.group = group_index(self.channels)
        self.ang = np.array([is_angle(c) for c in self.channels])
        W = np.clip(np.asarray(W, float), 0.0, W_MAX).copy()
        W[ROOT_POS] = 0.0    # root translation: hold/velocity only (module doc)
        W[:, :, -1] = 0.0    # q > 1.1: the HLM predicts what is observed worse than default does; it yields
        self.W, self.S = np.ascontiguousarray(W), np.ascontiguousarray(S, dtype=float)
        self.tau = float(tau)
        self.anchor = float(np.exp(-1.0 / self.tau)) if self.tau > 0 else 0.0
        self._anc = self.anchor if self.tau > 0 else 0.0   # the compiled mixing's: 0 = no anchoring
        self.meta = dict(meta or {})
        self._cols = [np.flatnonzero(self.group == g) for g in SHADOW_GROUPS]
        self._member = np.stack([self.group == g for g in SHADOW_GROUPS], 1).astype(np.float64)   # (C, groups)
        self._nonpos = self.group != ROOT_POS
        self._sgroup = np.full(len(self.channels), -1, np.int64)   # each channel's index into SHADOW_GROUPS
        for i, g in enumerate(SHADOW_GROUPS):
            self._sgroup[self.group == g] = i
        self._qe = Q_EDGES.tolist()
        self.compiled = jit.enabled()   # the compiled mixing (blend/withhlm_fast.py); else _mix_numpy
        self._direct = isinstance(default, DefaultModel)   # _blend_step calls its streams' compiled step
        C, TB = len(self.channels), len(T_EDGES) + 1
        self.calib = np.ones((C, TB)) if cal is None else calib.check(cal, C, TB, METHOD)   # blend/calib.py
        self._rows = np.arange(C)
        # the compiled mixing reads per-channel tables (channel j its own "group"): W of its group,
        # S of its group times its calibration, so the calibration costs nothing there (same fills)
        self._legs = np.flatnonzero(np.isin(self.group, LEG_GROUPS))
        self._lhid = [self._cols[j][self.ang[self._cols[j]]] for j in range(len(SHADOW_GROUPS))]   # a group's angles
        self.long_trust, self.long_gate = LONG_TRUST_OFF, LONG_GATE_OFF
        self._lq_max = self._lg_max = -math.inf
        self._lr_min = math.inf
        self._lg_rest = 0
        self._lg_on = False
        self.long_ll, self._ll_on, self._ll_a, self._ll_d = LONG_LL_OFF, False, 0.0, 0.0
        self.long_ll_legs, self._ll_c = False, 0
        self.set_long_trust(*_pair("long_trust", self.meta.get("long_trust", LONG_TRUST_OFF)))
        self.set_long_gate(*_pair("long_gate", self.meta.get("long_gate", LONG_GATE_OFF), 4))
        self.set_long_ll(*_pair("long_ll", self.meta.get("long_ll", LONG_LL_OFF)))
        self.set_long_ll_legs(self.meta.get("long_ll_legs", False))
        # the shadow bound's prior window (Q_PRIOR_AT), kept with the model: its W/S were fitted under it
        pa = self.meta.get("prior_at", Q_PRIOR_AT)
        if isinstance(pa, bool) or not isinstance(pa, int | float) or not math.isfinite(pa):
            raise FillerError(f"{METHOD}: 'prior_at' must be a finite number (got {pa!r})")
        self.prior_at = float(pa)
        self.meta["prior_at"] = self.prior_at
        self._kS = np.ascontiguousarray(self.S[self.group] * self.calib)
        self.rate_ref: np.ndarray | None = None   # the training data's mean |dx| a frame per channel ("Rate")
        self._ref = np.zeros(C)
        if rate_ref is not None:
            self.set_rate_ref(rate_ref)
        self.set_smooth(**(NO_SMOOTH if smooth is None else smooth))
        self.set_band_q(np.ones((len(GROUP_NAMES), len(Q_EDGES) + 1)) if band_q is None else band_q, band_gate)

    def set_long_trust(self, k: int, qmax: float) -> None:
        """The long-erasure trust (module doc, "Long erasures"): a channel outside the legs missing for
        >= ``k`` frames while every leg channel is observed and the stream's q+ <= ``qmax`` takes the
        share W of q bin 0.7-1.1 instead of the last bin's 0.  k = 0: off (the fills of main)."""
        k, qmax = _check_long("long_trust", k, qmax)
        if k > 0 and self.long_gate[0] > 0:
            raise FillerError(f"{METHOD}: long_trust and long_gate are alternatives; set one (long_gate is {self.long_gate!r})")
        self.long_trust = (k, qmax)
        self._lq_max = math.log(qmax) if k > 0 else -math.inf
        if k > 0:
            self.meta["long_trust"] = list(self.long_trust)
        else:
            self.meta.pop("long_trust", None)
        self._long_column(k)

    def set_long_gate(self, k: int, qlong: float, qrev: float = 0.0, rest: int = 0) -> None:
        """The leg gate (module doc, "Long erasures"): while more than SHADOW_MAX_MISS channels are
        missing and every leg channel is observed, long windows on the legs score the HLM into the
        stream's q_long+; a channel outside the legs and the root position missing for >= ``k`` frames,
        where the stream's q+ is in the last bin, takes the share W of q bin 0.7-1.1 while q_long+ <=
        ``qlong`` (0: never); and once a long window of this erasure is scored, q_long+ > ``qrev`` sends
        the stream to the last q bin (W = 0) whatever its q+ (0: never); ``rest`` frames between long
        windows (0: back to back).  k = 0: off (the fills of main)."""
        bad = any(isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x) or x < 0 for x in (qlong, qrev, rest))
        if bad or (k and not (qlong > 0 or qrev > 0)) or rest != int(rest):
            raise FillerError(f"{METHOD}: long_gate must be (k >= 0 whole frames, qlong >= 0, qrev >= 0, one of them > 0"
                              f"[, rest >= 0 whole frames]) (got {(k, qlong, qrev, rest)!r})")
        k, _ = _check_long("long_gate", k, 1.0)
        if k > 0 and self.long_trust[0] > 0:
            raise FillerError(f"{METHOD}: long_trust and long_gate are alternatives; set one (long_trust is {self.long_trust!r})")
        self.long_gate = (k, float(qlong), float(qrev), int(rest)) if k > 0 else LONG_GATE_OFF
        self._lg_rest = int(rest) if k > 0 else 0
        self._lg_max = math.log(qlong) if k > 0 and qlong > 0 else -math.inf
        self._lr_min = math.log(qrev) if k > 0 and qrev > 0 else math.inf
        self._lg_on = k > 0
        if k > 0:
            self.meta["long_gate"] = _gate_meta(self.long_gate)
        else:
            self.meta.pop("long_gate", None)
        self._long_column(k if k > 0 else self.long_trust[0])

    def set_long_ll(self, d: float, tau: float) -> None:
        """The legs' predictive likelihood revoke (module doc, "long_ll"): in a long erasure with every
        leg channel observed, once it has lasted LL_N0 frames, the stream's HLM share is revoked (the bound
        set to at least log SHADOW_REVOKE, the last q bin for the rest of the erasure) when the HLM's one-step
        predictive log-likelihood per observed feature, a decayed mean over ``tau`` frames from the erasure's
        onset, is more than ``d`` nats below the stream's baseline (its level on frames with <= SHADOW_MAX_MISS
        missing and q+ < 1.1 before the erasure).  d = 0: off (the fills of main)."""
        bad = any(isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x) or x < 0 for x in (d, tau))
        if bad or (d > 0 and tau <= 0):
            raise FillerError(f"{METHOD}: long_ll must be (d >= 0 nats a feature, tau > 0 frames where d > 0) (got {(d, tau)!r})")
        core = getattr(getattr(self.hlm, "pool", None), "core", {})
        if d > 0 and "ll" not in core:
            raise FillerError(f"{METHOD}: long_ll needs the HLM's predictive likelihood (hlm.online's \"ll\"), which {self.hlm.method} has not")
        self._hcore = core   # the HLM's state pool's arrays (the dict stays; its arrays are new when the pool grows)
        self.long_ll = (float(d), float(tau)) if d > 0 else LONG_LL_OFF
        self._ll_on = d > 0
        self._ll_a = math.exp(-1.0 / tau) if d > 0 else 0.0
        self._ll_d = float(d)
        if d > 0:
            self.meta["long_ll"] = list(self.long_ll)
        else:
            self.meta.pop("long_ll", None)
        self._ll_feats()

    def set_long_ll_legs(self, on: bool) -> None:
        """long_ll's baseline and erasure level on the legs' features only (``long_ll_legs``; loco-14): the HLM
        also keeps the normaliser over the observed leg features (its "ll" row's columns 2-3: the features whose
        every source channel is a leg channel, the channels the regime's "every leg channel observed" reads), and
        both the baseline and the level are that per observed leg feature, so they are the same quantity.  False
        (files without the key): both on every observed feature (loco-13, the fills of files written before)."""
        if not isinstance(on, bool):
            raise FillerError(f"{METHOD}: long_ll_legs must be true or false (got {on!r})")
        if on and not hasattr(self.hlm, "set_ll_feats"):
            raise FillerError(f"{METHOD}: long_ll_legs needs the HLM's partial normaliser, which {self.hlm.method} has not")
        self.long_ll_legs = on
        self._ll_c = 2 if on else 0   # the "ll" row's columns long_ll reads
        if on:
            self.meta["long_ll_legs"] = True
        else:
            self.meta.pop("long_ll_legs", None)
        self._ll_feats()

    def _ll_feats(self) -> None:
        """The HLM's partial normaliser on the leg features where long_ll reads it.  Never cleared here: the HLM
        may be shared by twins mixed anew (tests/default_small.py's remix), and its other outputs do not depend
        on it; an HLM loaded from a file without ``long_ll_legs`` never computes it (no extra work)."""
        hlm = self.hlm
        if self._ll_on and self.long_ll_legs:
            hlm.set_ll_feats(hlm.leg_feats(self._legs))   # type: ignore[attr-defined]

    def _ll_track(self, s: WithHLMState, o: np.ndarray) -> None:
        """long_ll (module doc): the stream's level and baseline from this frame's HLM step (its normaliser,
        ``hlm.online.init_state``'s "ll"), and the revoke.  After the HLM's step, before the q bin is read."""
        if s.busy and bool(o[self._legs].all()):   # the regime: no ordinary window runs
            ll, r, c = self._hcore["ll"], s.hs.slot, self._ll_c   # type: ignore[attr-defined]
            lln, no = ll.item(r, c), ll.item(r, c + 1)
            if not s.ll_in:   # the erasure's onset: its own level, the baseline frozen
                s.ll_in, s.ll_age, s.ll_S, s.ll_N, s.ll_rev = True, 0, 0.0, 0.0, False
                s.ll_B = s.ll_bS / s.ll_bN if s.ll_bN >= LL_BMIN else math.nan
            s.ll_age += 1
            if no > 0:
                s.ll_S = self._ll_a * s.ll_S + lln / no
                s.ll_N = self._ll_a * s.ll_N + 1.0
            if not s.ll_rev and s.ll_age >= LL_N0 and s.ll_N > 0 and s.ll_S / s.ll_N < s.ll_B - self._ll_d:
                s.ll_rev = True   # (nan baseline: never)
                s.n_llrev += 1
                s._lq = max(s._lq, LOG_REVOKE)
            return
        if s.ll_in:
            s.ll_in = s.ll_rev = False
        if s.busy or s._lq >= LOGQ_YIELD:
            return
        ll, r, c = self._hcore["ll"], s.hs.slot, self._ll_c   # the baseline: the HLM's share earned, ordinary windows run
        no = ll.item(r, c + 1)
        if no > 0:
            e = ll.item(r, c) / no
            bS, bN = s.ll_bS, s.ll_bN
            if bN >= 1.0:
                lo = bS / bN - LL_BCLIP
                if e < lo:
                    e = lo
            s.ll_bS = LL_BDECAY * bS + e
            s.ll_bN = LL_BDECAY * bN + 1.0

    def _long_column(self, k: int) -> None:
        """The compiled tables' extra q column (index len(Q_EDGES) + 1), the long bin."""
        Wl = self.W[:, :, -1].copy()   # the extra q bin: the last bin's shares (0) ...
        if k > 0:   # ... except a long gap outside the legs and root position: bin 0.7-1.1's
            tb0 = int(t_bin(np.array([k]))[0])
            body = [g for g in range(len(GROUP_NAMES)) if g not in LEG_GROUPS and g != ROOT_POS]
            Wl[body, tb0:] = self.W[body, tb0:, -2]
        self._W5 = np.ascontiguousarray(np.concatenate([self.W, Wl[:, :, None]], 2))
        self._kW = np.ascontiguousarray(self._W5[self.group])

    def _qb(self, s: WithHLMState, o: np.ndarray) -> int:
        """The q bin a stream's frame mixes with: the last bin becomes the long bin (index len(Q_EDGES) + 1)
        where the long-erasure trust holds (q+ <= qmax) or the leg gate does (in a long erasure, q_long+ <=
        qlong), every leg channel observed."""
        if s.ll_rev:   # long_ll's revoke: the blend alone, whatever else would open
            return len(self._qe)
        logq = s._lq
        if s.lbusy and self._lr_min < s.lg_lq < LOGQ_UNSCORED:   # the leg gate's revoke
            return len(self._qe)
        qb = bisect_right(self._qe, logq)
        if qb == len(self._qe) and (logq <= self._lq_max or (s.lbusy and s.lg_lq <= self._lg_max)) \
                and bool(o[self._legs].all()):
            return qb + 1
        return qb

    def _long(self, s: WithHLMState, f: np.ndarray, o: np.ndarray, busy: bool, gm: np.ndarray, compiled: bool) -> None:
        """The leg gate's long window for one stream's frame (module doc, "Long erasures"): plan it; where
        one is open, step the blend's and the HLM's twins (copies of the stream's states at the window's
        opening) with the leg hidden and score them on its angles.  Before the stream's own experts step."""
        g = s._plan_long(busy, gm)
        if g < 0:
            return
        lo = o.copy()
        lo[self._cols[g]] = False
        if s.ltwin is None:
            s.ltwin = _copy_state(s.ds)
            s.lhs = _fork_stream(self.hlm, s.hs, s.lhs)
        if compiled:
            T = self._blend_step(s.ltwin, f, lo).frame
        else:
            T = self.default.step_batch([s.ltwin], f[None], lo[None])[0].frame
        H = self.hlm.step_batch([s.lhs], np.ascontiguousarray(f[None]), lo[None])[0].frame
        hid = self._lhid[g]
        eh, e0 = wrap(H[hid] - f[hid]), wrap(T[hid] - f[hid])
        s._lscore(float((eh * eh).sum()), float((e0 * e0).sum()))

    def set_band_q(self, M: np.ndarray, gate: Any = None) -> None:
        """The band's multiplier per (group, q bin) (module doc, "Band q"; ones: off) and its rate gate
        (r0, r1) (None: ungated); fills unchanged."""
        M = np.asarray(M, dtype=float)
        shape = (len(GROUP_NAMES), len(Q_EDGES) + 1)
        if M.shape != shape or not np.isfinite(M).all() or (M <= 0).any():
            raise FillerError(f"{METHOD}: band_q must be {shape} finite numbers > 0 (got shape {M.shape})")
        if gate is not None:
            g = np.asarray(gate, dtype=float)
            if g.shape != (2,) or not np.isfinite(g).all() or (g < 0).any() or g[1] < g[0]:
                raise FillerError(f"{METHOD}: band_gate must be (r0, r1), finite, 0 <= r0 <= r1 (got {gate!r})")
            gate = g.copy()
        self.band_q, self.band_gate = M.copy(), gate
        self._kM = np.ascontiguousarray(np.concatenate([M, M[:, -1:]], 1)[self.group])   # per channel, as _kW (+ the long bin)
        self._qon = bool((M != 1.0).any())
        self._gpar = np.array([0.0, 0.0, 0.0]) if gate is None else np.array([gate[0], gate[1], 1.0])

    def set_smooth(self, knots: bool, pop: float, pop_tau: float = POP_TAU, pop_rel: float = POP_REL,
                   std_knots: bool = False, band_tau: float = 0.0, rate_a: float = 0.0,
                   pace_tau: float = 0.0, pace_k: float = PACE_K, pace_a: float = PACE_A) -> None:
        """The smoothing (module doc, "Smooth"): W and S read between the time bins' knots
        (``knots``; S alone with ``std_knots``), the pop limit of ``pop`` + ``pop_rel`` |last
        step| degrees a frame (pop 0: off) with its decay over ``pop_tau`` frames, and the band's
        share w low-passed over ``band_tau`` frames (0: off; the fill's w is not), and the band times
        the channel's observed rate against the training data's to the power ``rate_a`` (0: off; off
        too where the model has no ``rate_ref``), and the fill paced by the observed body's rate over
        ``pace_tau`` frames against its rate at the gap's onset (module doc, "Pace"; 0: off; off too
        without ``rate_ref``), 1 while at least ``pace_k`` x it (> 0) or at least ``pace_a`` (x rate_ref; 0: no such level).  Applies to a stream's gaps from
        their first frame on."""
        if not isinstance(std_knots, bool):
            raise FillerError(f"{METHOD}: smooth 'std_knots' must be true or false (got {std_knots!r})")
        if not isinstance(knots, bool):
            raise FillerError(f"{METHOD}: smooth 'knots' must be true or false (got {knots!r})")
        for name, v in (("pop", pop), ("pop_tau", pop_tau), ("pop_rel", pop_rel), ("band_tau", band_tau), ("rate_a", rate_a),
                        ("pace_tau", pace_tau), ("pace_k", pace_k), ("pace_a", pace_a)):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise FillerError(f"{METHOD}: smooth '{name}' must be a finite number >= 0 (got {v!r})")
        if pop > 0 and pop_tau <= 0:
            raise FillerError(f"{METHOD}: smooth 'pop_tau' must be > 0 when 'pop' is on (got {pop_tau!r})")
        if pace_tau > 0 and pace_k <= 0:
            raise FillerError(f"{METHOD}: smooth 'pace_k' must be > 0 when 'pace_tau' is on (got {pace_k!r})")
        self.smooth = {"knots": knots, "std_knots": std_knots, "pop": float(pop), "pop_tau": float(pop_tau),
                       "pop_rel": float(pop_rel), "band_tau": float(band_tau), "rate_a": float(rate_a),
                       "pace_tau": float(pace_tau), "pace_k": float(pace_k), "pace_a": float(pace_a)}
        self.bdecay = float(np.exp(-1.0 / band_tau)) if band_tau > 0 else 0.0
        self.knots = T_KNOTS.copy() if knots or std_knots else np.zeros(0)
        self._wk = knots
        self.pop, self.prel = float(pop), float(pop_rel)
        self.pdecay = float(np.exp(-1.0 / pop_tau)) if pop > 0 else 0.0
        self._set_rate()

    def set_scale(self, S: np.ndarray) -> None:
        """A new std scale S (G, T) (a refit, bench/band12_refit.py); fills unchanged."""
        S = np.asarray(S, dtype=float)
        if S.shape != self.S.shape or not np.isfinite(S).all() or (S <= 0).any():
            raise FillerError(f"{METHOD}: S must be {self.S.shape} finite numbers > 0 (got shape {S.shape})")
        self.S = np.ascontiguousarray(S)
        self._kS = np.ascontiguousarray(self.S[self.group] * self.calib)

    def set_rate_ref(self, ref: np.ndarray) -> None:
        """The training data's mean |dx| a frame per channel (``rate_ref``, module doc "Rate")."""
        ref = np.asarray(ref, dtype=float)
        if ref.shape != (self.n_channels,) or not np.isfinite(ref).all() or (ref < 0).any():
            raise FillerError(f"{METHOD}: rate_ref must be {self.n_channels} finite numbers >= 0 (got shape {ref.shape})")
        self.rate_ref = ref.copy()
        self._ref = np.ascontiguousarray(ref)
        if hasattr(self, "smooth"):
            self._set_rate()

    def _set_rate(self) -> None:
        """The compiled mixing's (decay, a, lo, hi): a = 0 where the model has no rate_ref."""
        a = self.smooth["rate_a"] if self.rate_ref is not None else 0.0
        self._rpar = np.array([math.exp(-1.0 / RATE_TAU), a, RATE_LO, RATE_HI])
        self._rdecay, self._rate_on = float(self._rpar[0]), a > 0   # (read per stream-frame: plain scalars)
        pt = self.smooth["pace_tau"] if self.rate_ref is not None else 0.0
        self._ppar = np.array([math.exp(-1.0 / pt) if pt > 0 else 0.0, math.exp(-1.0 / RATE_TAU), self.smooth["pace_k"],
                               self.smooth["pace_a"]])
        self._pace_on = pt > 0

    def stream(self) -> WithHLMState:
        return WithHLMState(self)

    def step_batch(self, states, frames, observed, level=None):
        mine = all(isinstance(s, WithHLMState) and s.m is self for s in states)
        if not mine or not states:
            return super().step_batch(states, frames, observed, level)
        if self.compiled and _ready(frames, np.float64, (len(states), self.n_channels)) \
                and _ready(observed, np.bool_, frames.shape) and observed_finite(frames, observed):
            return self._step(states, frames, observed)   # checked as checked_batch does, compiled
        F, O = checked_batch(len(states), self.n_channels, frames, observed)
        return self._step(states, F, O)

    def step_block(self, states, frames, observed, level=None):
        """``step_batch``'s fills as (n, C) arrays (the daemon's bundle path): where the compiled
        mixing serves (``_step_compiled``'s case), each stream's fill and std are written by
        ``mix_row`` straight into rows of the block, the blend's own into scratch rows
        (``_step_into``), the HLM's by its ``step_block``: no Fill per stream (``_step_block``).
        Otherwise ``step_batch``'s Fills stacked (``Model.step_block``).  Same numbers either way
        (tests/test_default_step_block.py)."""
        n = len(states)
        if level is None and n and self.compiled and self._direct and self.default.compiled \
                and all(type(s) is WithHLMState and s.m is self and not s.collect and not s.ds.collect for s in states) \
                and _ready(frames, np.float64, (n, self.n_channels)) and _ready(observed, np.bool_, frames.shape) \
                and observed_finite(frames, observed):
            return self._step_block(states, frames, observed)
        return super().step_block(states, frames, observed, level)

    def _step_block(self, states: list[WithHLMState], F: np.ndarray, O: np.ndarray) -> BlockFill:
        """_step_compiled into arrays, in its order: stream by stream the plan and the blend's
        step (a window's twin copied first, then stepped after the stream's own), the HLM's
        block, the compiled mixing a row each."""
        n, C = F.shape
        HO = O
        D, Dsd = np.empty((n, C)), np.empty((n, C))
        T = Tsd = None
        tw: list[int] = []
        for i, s in enumerate(states):
            nm = shadow_counts(O[i], self._nonpos, self._sgroup, s.gm)
            g = s._plan(nm > SHADOW_MAX_MISS, s.gm)
            if self._lg_on:   # the leg gate's long window ("Long erasures")
                self._long(s, F[i], O[i], nm > SHADOW_MAX_MISS, s.gm, True)
            if g >= 0:
                HO = O.copy() if HO is O else HO
                HO[i, self._cols[g]] = False
                if s.twin is None:
                    s.twin = _copy_state(s.ds)
            s.ds._step_into(F[i], O[i], D[i], Dsd[i])   # type: ignore[attr-defined]
            if g >= 0:
                if T is None:
                    T, Tsd = np.empty((n, C)), np.empty((n, C))
                s.twin._step_into(F[i], HO[i], T[i], Tsd[i])   # type: ignore[union-attr]
                tw.append(i)
        hb = self.hlm.step_block([s.hs for s in states], F, HO)
        H, Hsd = hb.frame, hb.std
        out, std = np.empty((n, C)), np.empty((n, C))
        j = 0
        for i, s in enumerate(states):
            has = j < len(tw) and tw[j] == i
            j += has
            if self._ll_on:   # long_ll, from this frame's HLM step
                self._ll_track(s, O[i])
            qb = self._qb(s, O[i])
            eh, e0, nh = mix_row(F[i], O[i], HO[i], D[i], Dsd[i], H[i], Hsd[i], T[i] if has else D[i],   # type: ignore[index]
                                 has, self.ang, self._rows, self._kW, self._kS, T_EDGES, qb,
                                 self._anc, s.k, s.o, out[i], std[i], self.knots, self._wk, self.pop, self.prel, self.pdecay, s.rp, s.vp, s.e,
                                 self.bdecay, s.wb)
            if self._qon:   # band_q ("Band q")
                q_band(F[i], O[i], self.ang, std[i], s.k, self._kM, qb, self.bdecay, s.mb,
                       self._gpar, self._ref, s.rst, self._rdecay, not self._rate_on, s.buf)
            if self._rate_on:   # the band's rate ("Rate")
                rate_band(F[i], O[i], self.ang, std[i], self._rpar, self._ref, s.rst)
            if self._pace_on:   # the fill paced by the observed body ("Pace")
                pace_row(F[i], O[i], self.ang, out[i], s.k, self._ref, s.ps, s.pz, s.py, s.pr, self._ppar, s.buf)
            if has and nh:
                s._score(eh, e0)
        return BlockFill(out, std, ~O, hb.style, hb.phase)

    def _step(self, states: list[WithHLMState], F: np.ndarray, O: np.ndarray) -> list[Fill]:
        """Every stream of the batch at once: plan the shadow masks, step each expert (the twins of
        the streams in a shadow window beside ``default``'s own streams), then mix (module doc):
        compiled per stream where numba runs (_step_compiled), else as (n, C) arrays."""
        if self.compiled and not any(s.collect for s in states):
            return self._step_compiled(states, F, O)
        n = len(states)
        win: list[int] = []
        busy = ((~O) & self._nonpos).sum(1) > SHADOW_MAX_MISS
        gmiss = (~O).astype(np.float64) @ self._member            # (n, shadow groups) channels missing
        HO = O.copy()
        for i, s in enumerate(states):
            g = s._plan(bool(busy[i]), gmiss[i])
            if self._lg_on:   # the leg gate's long window ("Long erasures")
                self._long(s, F[i], O[i], bool(busy[i]), gmiss[i], False)
            self._open(s, g, i, HO, win)
        if win:
            dst = [s.ds for s in states] + [t for t in (states[i].twin for i in win) if t is not None]   # (_open set them)
            dfills = self.default.step_batch(dst, np.concatenate([F, F[win]]), np.concatenate([O, HO[win]]))
            twin = {i: dfills[n + r].frame for r, i in enumerate(win)}
        else:
            dfills = self.default.step_batch([s.ds for s in states], F, O)
            twin = {}
        hfills = self.hlm.step_batch([s.hs for s in states], F, HO)
        return self._mix_numpy(states, F, O, HO, dfills, hfills, twin)

    def _step_compiled(self, states: list[WithHLMState], F: np.ndarray, O: np.ndarray) -> list[Fill]:
        """_step where numba runs: stream by stream the plan, the blend's own compiled step on its
        stream and (window open) on its twin, called directly (F and O were checked once for the
        batch: no second check, no concatenated batch), the HLM's batch, the compiled mixing.
        The order is _step's: a window's twin is copied before the stream's blend steps."""
        HO = O
        dfills: list[Fill] = []
        twin: dict[int, np.ndarray] = {}
        for i, s in enumerate(states):
            nm = shadow_counts(O[i], self._nonpos, self._sgroup, s.gm)
            g = s._plan(nm > SHADOW_MAX_MISS, s.gm)
            if self._lg_on:   # the leg gate's long window ("Long erasures")
                self._long(s, F[i], O[i], nm > SHADOW_MAX_MISS, s.gm, True)
            if g >= 0:
                HO = O.copy() if HO is O else HO
                HO[i, self._cols[g]] = False
                if s.twin is None:
                    s.twin = _copy_state(s.ds)
            dfills.append(self._blend_step(s.ds, F[i], O[i]))
            if g >= 0:
                twin[i] = self._blend_step(s.twin, F[i], HO[i]).frame   # type: ignore[arg-type]
        hfills = self.hlm.step_batch([s.hs for s in states], F, HO)
        return self._mix_fast(states, F, O, HO, dfills, hfills, twin)

    def _blend_step(self, ds: FillerState, f: np.ndarray, o: np.ndarray) -> Fill:
        """One blend stream's step on a checked row: its compiled step itself where it has one."""
        if self._direct and self.default.compiled and not ds.collect:   # type: ignore[attr-defined]
            return ds._step_fast(f, o)   # type: ignore[attr-defined]
        return self.default.step_batch([ds], f[None], o[None])[0]

    def _open(self, s: WithHLMState, g: int, i: int, HO: np.ndarray, win: list[int]) -> None:
        """Hide shadow group g of stream i from the HLM and the twin; a window's twin starts as a
        copy of the stream's own ``default`` state (the same history, the group hidden from now on)."""
        if g < 0:
            return
        HO[i, self._cols[g]] = False
        if s.twin is None:
            s.twin = _copy_state(s.ds)
        win.append(i)

    def _mix_fast(self, states, F, O, HO, dfills, hfills, twin) -> list[Fill]:
        fills = []
        C = self.n_channels
        for i, s in enumerate(states):
            d, h = dfills[i], hfills[i]
            if self._ll_on:   # long_ll, from this frame's HLM step
                self._ll_track(s, O[i])
            logq = s.logq
            T = twin.get(i)
            out, std = np.empty(C), np.empty(C)
            qb = self._qb(s, O[i])
            eh, e0, nh = mix_row(F[i], O[i], HO[i], d.frame, d.std, h.frame, h.std, d.frame if T is None else T,
                                 T is not None, self.ang, self._rows, self._kW, self._kS, T_EDGES, qb,
                                 self._anc, s.k, s.o, out, std, self.knots, self._wk, self.pop, self.prel, self.pdecay, s.rp, s.vp, s.e,
                                 self.bdecay, s.wb)
            if self._qon:   # band_q ("Band q")
                q_band(F[i], O[i], self.ang, std, s.k, self._kM, qb, self.bdecay, s.mb,
                       self._gpar, self._ref, s.rst, self._rdecay, not self._rate_on, s.buf)
            if self._rate_on:   # the band's rate ("Rate")
                rate_band(F[i], O[i], self.ang, std, self._rpar, self._ref, s.rst)
            if self._pace_on:   # the fill paced by the observed body ("Pace")
                pace_row(F[i], O[i], self.ang, out, s.k, self._ref, s.ps, s.pz, s.py, s.pr, self._ppar, s.buf)
            if T is not None and nh:
                s._score(eh, e0)
            fills.append(Fill(out, std, d.filled, {**h.extras, "hlm_q": math.exp(logq)}))   # d.filled: ~O[i]
        return fills

    def _mix_numpy(self, states, F, O, HO, dfills, hfills, twin) -> list[Fill]:
        """The reference mixing, as (n, C) arrays (tests/test_default_hlm_fast.py checks the compiled
        one against it); the tuning's ``collect`` reads its parts."""
        n = len(states)
        Df, Dsd = np.stack([f.frame for f in dfills[:n]]), np.stack([f.std for f in dfills[:n]])
        Hf, Hsd = np.stack([f.frame for f in hfills]), np.stack([f.std for f in hfills])
        for i, T in twin.items():
            s = states[i]
            hid = O[i] & ~HO[i] & self.ang
            if hid.any():
                eh, e0 = wrap(Hf[i, hid] - F[i, hid]), wrap(T[hid] - F[i, hid])
                s._score(float((eh * eh).sum()), float((e0 * e0).sum()))
        K = np.where(O, 0, np.stack([s.k for s in states]) + 1)
        if self._ll_on:   # long_ll, from this frame's HLM step
            for i, s in enumerate(states):
                self._ll_track(s, O[i])
        logq = np.array([s.logq for s in states])
        raw = np.where(self.ang, wrap(Hf - Df), Hf - Df)
        off = np.where(K == 1, -raw, np.stack([s.o for s in states]))
        diff = raw + (off * self.anchor ** np.maximum(K - 1, 0) if self.tau > 0 else 0.0)
        qb = np.array([self._qb(s, O[i]) for i, s in enumerate(states)])[:, None]
        tb = t_bin(K)
        w = np.where(O, 0.0, self._W5[self.group[None, :], tb, qb])
        sc = self.S[self.group[None, :], tb]
        if len(self.knots):   # S, and W where knots, between the knots (module doc, "Smooth")
            Kc = np.clip(K, self.knots[0], self.knots[-1]).astype(float)
            lo = np.clip(np.searchsorted(self.knots, Kc, side="right") - 1, 0, len(self.knots) - 2)
            f = (Kc - self.knots[lo]) / (self.knots[lo + 1] - self.knots[lo])
            kS = self._kS[self._rows[None, :]]
            sc = np.take_along_axis(kS, lo[..., None], -1)[..., 0] * (1 - f) + np.take_along_axis(kS, lo[..., None] + 1, -1)[..., 0] * f
            if self._wk:
                kW = self._kW[self._rows[None, :], :, qb]
                w = np.take_along_axis(kW, lo[..., None], -1)[..., 0] * (1 - f) + np.take_along_axis(kW, lo[..., None] + 1, -1)[..., 0] * f
                w = np.where(O, 0.0, w)
        y = Df + w * diff
        if self.pop > 0:   # the pop limit (module doc, "Smooth")
            rp, vp, e = (np.stack([getattr(s, a) for s in states]) for a in ("rp", "vp", "e"))
            jump = y - (rp + vp)
            lim = self.pop + self.prel * np.abs(vp)
            x = np.where(K >= 3, jump - np.clip(jump, -lim, lim), 0.0)
            e = np.where(K >= 3, e * self.pdecay - x, 0.0)
            vp = np.where(K == 1, 0.0, y - rp - x)
            rp = y
            for a, v in (("rp", rp), ("vp", vp), ("e", e)):
                for i, s in enumerate(states):
                    setattr(s, a, np.where(O[i], getattr(s, a), v[i]))
            out = np.where(O, F, y + e)
        else:
            out = np.where(O, F, y)
        if self.bdecay > 0:   # the band's share, low-passed from the gap's second frame on ("Smooth")
            wb = np.stack([s.wb for s in states])
            wb = np.where(K == 1, w, wb + (w - wb) * (1.0 - self.bdecay))
            for i, s in enumerate(states):
                s.wb = np.where(O[i], s.wb, wb[i])
            w = np.where(O, 0.0, wb)
        var = (1 - w) * Dsd ** 2 + w * Hsd ** 2 + w * (1 - w) * diff ** 2
        if len(self.knots):
            std = np.where(O, 0.0, sc * np.sqrt(var))
        else:
            std = np.where(O, 0.0, sc * np.sqrt(var)) * self.calib[self._rows, tb]
        if self._qon:   # band_q, from the rates before this frame's update ("Band q")
            mfac = self._q_factor(states, K, qb[:, 0], O)
        if self._rate_on:   # the band times the channel's rate ("Rate")
            std = std * self._rate_factor(states, F, O)
        elif self._qon:
            self._rate_factor(states, F, O)   # only its update of the rates
        if self._qon:
            std = std * mfac
        if self._pace_on:   # the fill paced by the observed body ("Pace")
            out = self._pace(states, F, O, K, out)
        fills = []
        for i, s in enumerate(states):
            s.k, s.o = K[i].copy(), off[i].copy()
            if s.collect:
                j = np.flatnonzero(~O[i])
                s.comp = None if not len(j) else {
                    "idx": j, "k": K[i, j], "D": Df[i, j], "H": Df[i, j] + raw[i, j], "o": off[i, j], "sD": Dsd[i, j],
                    "sH": Hsd[i, j], "logq": np.full(len(j), logq[i])}
            fills.append(Fill(out[i], std[i], ~O[i], {**hfills[i].extras, "hlm_q": float(np.exp(logq[i]))}))
        return fills

    def _q_factor(self, states, K, qb, O) -> np.ndarray:
        """The numpy path's band_q (module doc, "Band q"; q_band's arithmetic): each missing channel's
        low-passed 1 + (band_q - 1) gate, the gate from the stream's rate before this frame."""
        n = len(states)
        gate = np.ones(n)
        if self._gpar[2] > 0:
            r0, r1 = self._gpar[0], self._gpar[1]
            for i, s in enumerate(states):
                rs, rn = s.rst[0], s.rst[1]
                ok = self.ang & (self._ref > 0) & (rn >= 1.0)
                if not ok.any():
                    gate[i] = 0.0
                    continue
                r = float(np.median(rs[ok] / rn[ok] / self._ref[ok]))
                gate[i] = 1.0 if r <= r0 else 0.0 if r >= r1 else (r1 - r) / (r1 - r0)
        m = 1.0 + (self._kM[:, qb].T - 1.0) * gate[:, None]          # (n, C)
        mb = np.stack([s.mb for s in states])
        mb = np.where((K == 1) | (self.bdecay <= 0), m, mb + (m - mb) * (1.0 - self.bdecay))
        for i, s in enumerate(states):
            s.mb = np.where(O[i], s.mb, mb[i])
        return np.where(O, 1.0, mb)

    def _pace(self, states, F, O, K, out) -> np.ndarray:
        """The numpy path's pace (module doc, "Pace"; pace_row's arithmetic): the observed channels'
        fast and slow rates updated, then each missing channel's fill moves its own step times
        s = clip(R / ref, 0, 1), ref = pace_k r0 (or the smaller of it and pace_a where pace_a > 0), from
        where it was (from its last value on a gap's first frame)."""
        fd, sd, kf, pa = (float(x) for x in self._ppar)
        out = out.copy()
        for i, s in enumerate(states):
            ps, o = s.ps, O[i]
            dx = np.where(o, F[i], ps[4]) - ps[4]   # (a missing value may be nan)
            dx = np.abs(np.where(self.ang, wrap(dx), dx))
            upd = o & (ps[5] > 0)
            f1, s1 = ps[0] * fd + dx, ps[2] * sd + dx
            f1[f1 < RATE_FTZ] = 0.0
            s1[s1 < RATE_FTZ] = 0.0
            ps[0], ps[1] = np.where(upd, f1, ps[0]), np.where(upd, ps[1] * fd + 1.0, ps[1])
            ps[2], ps[3] = np.where(upd, s1, ps[2]), np.where(upd, ps[3] * sd + 1.0, ps[3])
            ps[4] = np.where(o, F[i], ps[4])
            ok = o & self.ang & (self._ref > 0)
            r = _median_rate(ps[0], ps[1], self._ref, ok)
            miss = ~o
            onset = miss & (K[i] == 1)
            if onset.any():
                r0 = _median_rate(ps[2], ps[3], self._ref, ok)
                had = onset & (ps[5] > 0)
                s.pr = np.where(had, r0, np.where(onset, -1.0, s.pr))
                s.pz = np.where(had, ps[4], np.where(onset, out[i], s.pz))
                s.py = np.where(had, ps[4], np.where(onset, out[i], s.py))
            ps[5] = np.where(o, 1.0, 0.0)
            ok0 = (r >= 0) & (s.pr > 0)
            den = kf * np.where(ok0, s.pr, 1.0)
            if pa > 0:
                den = np.minimum(den, pa)
            sc = np.where(ok0, np.clip(r / den, 0.0, 1.0), 1.0)
            d = out[i] - s.py
            d = np.where(self.ang, wrap(d), d)
            z = s.pz + sc * d
            s.pz = np.where(miss, z, s.pz)
            s.py = np.where(miss, out[i], s.py)
            out[i] = np.where(miss, z, out[i])
        return out

    def _rate_factor(self, states, F, O) -> np.ndarray:
        """The numpy path's rate (module doc, "Rate"; mix_row's arithmetic): each missing channel's
        factor clip((rate / ref)^a, lo, hi) from the frames before this one (1 where observed, or
        with under one value's weight of history), then the observed channels' rates updated."""
        rdecay, a, lo, hi = (float(x) for x in self._rpar)
        rst = np.stack([s.rst for s in states])           # (n, 4, C)
        rs, rn, rl, rv = rst[:, 0], rst[:, 1], rst[:, 2], rst[:, 3]
        ok = ~O & (rn >= 1.0) & (self._ref > 0)
        r = np.divide(rs, np.where(ok, rn, 1.0)) / np.where(self._ref > 0, self._ref, 1.0)
        fac = np.where(ok, np.clip(np.where(ok, r, 1.0) ** a, lo, hi), 1.0)
        Fo = np.where(O, F, rl)
        dx = np.abs(np.where(self.ang, wrap(Fo - rl), Fo - rl))
        upd = O & (rv > 0)
        rs1 = rs * rdecay + dx
        rs1[rs1 < RATE_FTZ] = 0.0   # subnormals (withhlm_fast._ftz)
        new = np.stack([np.where(upd, rs1, rs), np.where(upd, rn * rdecay + 1.0, rn), Fo,
                        np.where(O, 1.0, 0.0)], 1)
        for i, s in enumerate(states):
            s.rst = new[i].copy()
        return fac

    def info(self) -> dict[str, Any]:
        return {**super().info(), "experts": [self.default.method, self.hlm.method]}

    # ---- persistence: both experts' arrays in one file, prefixed d/ and h/ ------------------------
    def save(self, path: str) -> None:
        parts: dict[str, Any] = {}
        arrays: dict[str, np.ndarray] = {"W": self.W, "S": self.S, "calib": self.calib}
        if self.rate_ref is not None:
            arrays["rate_ref"] = self.rate_ref
        if self._qon:
            arrays["band_q"] = self.band_q
            if self.band_gate is not None:
                arrays["band_gate"] = self.band_gate
        with tempfile.TemporaryDirectory() as tmp:
            for key, m in (("d", self.default), ("h", self.hlm)):
                p = str(Path(tmp) / f"{key}.npz")
                m.save(p)
                meta, arr = modelfile.load_arrays(p)
                parts[key] = meta
                arrays.update({f"{key}/{k}": v for k, v in arr.items()})
        meta = {**self.meta, "method": METHOD, "channels": self.channels, "experts": parts, "tau": self.tau,
                "smooth": self.smooth,
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
        from hlm.model import load as load_hlm

        sub = {key: {k[2:]: v for k, v in arrays.items() if k.startswith(key + "/")} for key in ("d", "h")}
        d = DefaultModel.load(path, parts["d"], sub["d"])
        h = load_hlm(path, parts["h"], sub["h"])
        G, TB, QB = len(GROUP_NAMES), len(T_EDGES) + 1, len(Q_EDGES) + 1
        W = modelfile.require(path, arrays, "W", (G, TB, QB))
        S = modelfile.require(path, arrays, "S", (G, TB))
        cal = modelfile.require(path, arrays, "calib", (len(d.channels), TB)) if "calib" in arrays else None   # older: 1
        ref = modelfile.require(path, arrays, "rate_ref", (len(d.channels),)) if "rate_ref" in arrays else None   # older: off
        bq = modelfile.require(path, arrays, "band_q", (G, QB)) if "band_q" in arrays else None   # older: ones (off)
        bg = modelfile.require(path, arrays, "band_gate", (2,)) if "band_gate" in arrays else None
        if list(meta["channels"]) != list(d.channels):
            raise modelfile.ModelFileError(f"{path}: channel list does not match its experts'")
        tau = meta.get("tau", ANCHOR_TAU)
        if not isinstance(tau, int | float) or tau < 0:
            raise modelfile.ModelFileError(f"{path}: {METHOD} 'tau' must be a number >= 0 (got {tau!r})")
        smooth = meta.get("smooth", NO_SMOOTH)   # files written before smoothing: off, as they were
        if isinstance(smooth, dict):   # ... and before one of its keys: that key off
            smooth = {**{k: v for k, v in SMOOTH_SINCE.items() if k not in smooth}, **smooth}
        if not isinstance(smooth, dict) or set(smooth) != set(NO_SMOOTH):
            raise modelfile.ModelFileError(f"{path}: {METHOD} 'smooth' must be a table of {sorted(NO_SMOOTH)} (got {smooth!r})")
        kept = {k: v for k, v in meta.items() if k not in ("experts", "bins", "channels", "method", "tau", "smooth")}
        kept.setdefault("prior_at", 0.0)   # files written before the prior moved to the cut: as they filled
        try:
            return cls(d, h, W, S, kept, float(tau), cal, smooth, ref, bq, bg)
        except FillerError as e:
            raise modelfile.ModelFileError(f"{path}: {e}") from None


class WithHLMState(FillerState):
    """One stream: each expert's own state, frames since onset, and the shadow check."""

    def __init__(self, model: WithHLMModel):
        self.m = model
        C = model.n_channels
        self.ds = model.default.stream()
        self.twin: FillerState | None = None   # default under the shadow mask, for one window (module doc)
        self.gm = np.zeros(len(SHADOW_GROUPS))   # scratch: each shadow group's missing channels
        self.hs = model.hlm.stream()
        self.k = np.zeros(C, np.int64)
        self.o = np.zeros(C)         # the HLM's anchoring offset (module doc)
        self.rp, self.vp, self.e = np.zeros(C), np.zeros(C), np.zeros(C)   # the pop limit's course and offset ("Smooth")
        self.wb = np.zeros(C)        # the band's low-passed share w ("Smooth", band_tau)
        self.rst = np.zeros((4, C))  # each channel's decayed sum of |dx|, of 1, last value, last observed ("Rate")
        self.mb = np.ones(C)         # band_q's low-passed multiplier ("Band q")
        self.buf = np.zeros(C)       # scratch for the stream's rate ("Band q", "Pace")
        self.ps = np.zeros((6, C))   # the pace's fast and slow decayed sums of |dx| and of 1, last value, observed ("Pace")
        self.pz, self.py, self.pr = np.zeros(C), np.zeros(C), np.zeros(C)   # the paced fill, the fill, the onset rate ("Pace")
        self.lr_sum = self.lr_ss = self.lr_n = 0.0   # decayed sums of the windows' log r, log r^2, count
        self._lq = LOGQ_UNSCORED     # the pessimistic bound on log q (module doc), updated as windows close
        self.sh = -1                 # index into SHADOW_GROUPS of the hidden group, -1: none
        self.sh_n = SHADOW_WARM      # frames into the window (or, with sh = -1, the pause left)
        self.n_win = 0               # windows scored
        self.sh_next = 0             # the next group to hide
        self.eh = self.e0 = 0.0
        # the leg gate's long windows (module doc, "Long erasures"): as the check's, on the legs, in long erasures
        self.lbusy = False           # this frame is in a long erasure (more than SHADOW_MAX_MISS missing)
        self.lsh, self.lsh_n, self.lsh_next = -1, 0, 0   # the hidden leg (index into SHADOW_GROUPS), frames, next
        self.leh = self.le0 = 0.0
        self.llr_sum = self.llr_ss = self.llr_n = 0.0
        self.lg_lq = LOGQ_UNSCORED   # q_long+'s log: this erasure's evidence only
        self.n_lwin = 0
        self.ltwin: FillerState | None = None   # the blend under the long window's mask
        self.lhs: FillerState | None = None     # the HLM under it (its slot kept between windows)
        # long_ll (module doc): the erasure's level, the baseline, the revoke
        self.busy = False   # this frame: more than SHADOW_MAX_MISS channels missing (set by _plan)
        self.ll_in = self.ll_rev = False
        self.ll_age, self.n_llrev = 0, 0
        self.ll_S = self.ll_N = self.ll_bS = self.ll_bN = 0.0
        self.ll_B = math.nan
        self.collect = False         # bench/default_hlm_tune.py reads ``comp`` after each step
        self.comp: dict[str, np.ndarray] | None = None

    @property
    def logq(self) -> float:
        """The pessimistic bound on log q that picks the q bin (module doc); LOGQ_UNSCORED until a
        window has been scored."""
        return self._lq

    def _score(self, eh: float, e0: float) -> None:
        """One frame of an open window: the HLM's and the twin's squared errors on the hidden angles;
        the window's first SHADOW_SKIP frames are counted, not scored."""
        self.sh_n += 1
        if self.sh_n > SHADOW_SKIP:
            self.eh += eh
            self.e0 += e0

    def _close(self) -> None:
        if self.sh_n - SHADOW_SKIP >= SHADOW_MIN and self.e0 > 0:
            self.lr_sum, self.lr_ss, self.lr_n, self._lq = _bound(self.lr_sum, self.lr_ss, self.lr_n, self.eh, self.e0,
                                                                   self.m.prior_at)
            self.n_win += 1
        rest = SHADOW_PAUSE if self.n_win >= SHADOW_EAGER else 0
        self.sh, self.sh_n, self.eh, self.e0, self.twin = -1, rest, 0.0, 0.0, None

    def _plan(self, busy: bool, gmiss: np.ndarray) -> int:
        """This frame's hidden group (index into SHADOW_GROUPS) or -1; opens and closes windows.
        ``busy``: more than SHADOW_MAX_MISS channels really missing; ``gmiss``: each shadow group's
        missing channels."""
        self.busy = busy   # (read by long_ll's _ll_track later in the step)
        if self.sh >= 0:
            if busy or gmiss[self.sh] > 0 or self.sh_n >= SHADOW_LEN:
                self._close()
        elif self.sh_n > 0:
            self.sh_n -= 1
        elif not busy:
            for i in range(len(SHADOW_GROUPS)):
                g = (self.sh_next + i) % len(SHADOW_GROUPS)
                if len(self.m._cols[g]) and gmiss[g] == 0:
                    self.sh, self.sh_n, self.sh_next = g, 0, (g + 1) % len(SHADOW_GROUPS)
                    break
        return self.sh

    def _lscore(self, eh: float, e0: float) -> None:
        """One frame of an open long window (as ``_score``)."""
        self.lsh_n += 1
        if self.lsh_n > SHADOW_SKIP:
            self.leh += eh
            self.le0 += e0

    def _lclose(self) -> None:
        if self.lsh_n - SHADOW_SKIP >= SHADOW_MIN and self.le0 > 0:
            self.llr_sum, self.llr_ss, self.llr_n, self.lg_lq = _bound(self.llr_sum, self.llr_ss, self.llr_n, self.leh, self.le0,
                                                                       self.m.prior_at)
            self.n_lwin += 1
        self.lsh, self.lsh_n, self.leh, self.le0, self.ltwin = -1, self.m._lg_rest, 0.0, 0.0, None

    def _plan_long(self, busy: bool, gmiss: np.ndarray) -> int:
        """This frame's long window (index into SHADOW_GROUPS of the hidden leg) or -1: only in a long
        erasure (``busy``) with every leg channel observed; legs in turn, back to back; the bound starts
        unscored at each long erasure's onset; ``rest`` frames (long_gate's fourth value) between windows,
        counted in long-erasure frames, the first window at the onset."""
        if not busy:
            if self.lsh >= 0:
                self._lclose()
            self.lbusy = False
            return -1
        if not self.lbusy:   # a long erasure's onset: its own evidence only
            self.lbusy = True
            self.llr_sum = self.llr_ss = self.llr_n = 0.0
            self.lg_lq = LOGQ_UNSCORED
            self.lsh_next = 0
            if self.lsh < 0:
                self.lsh_n = 0
        legs = all(gmiss[j] == 0 for j in LEG_SHADOW)
        if self.lsh >= 0 and (not legs or self.lsh_n >= SHADOW_LEN):
            self._lclose()
        if self.lsh < 0 and self.lsh_n > 0:
            self.lsh_n -= 1
        elif self.lsh < 0 and legs:
            self.lsh, self.lsh_n = LEG_SHADOW[self.lsh_next], 0
            self.lsh_next = 1 - self.lsh_next
        return self.lsh

    def step(self, frame, observed=None) -> Fill:
        f, obs = check_frame(frame, observed, self.m.n_channels)
        return self.m._step([self], f[None], obs[None])[0]


def _bound(lr_sum: float, lr_ss: float, lr_n: float, eh: float, e0: float, prior_at: float) -> tuple[float, float, float, float]:
    """A window's r = eh / e0 into the decayed sums; (sums, the bound on log q) (module doc); ``prior_at``:
    the log r of the Q_PRIOR_N prior windows (the model's ``prior_at``, Q_PRIOR_AT for a new one)."""
    r = min(max(math.log(max(eh, 1e-9) / max(e0, 1e-9)), -4.0), 4.0)
    lr_sum = Q_DECAY * lr_sum + r
    lr_ss = Q_DECAY * lr_ss + r * r
    lr_n = Q_DECAY * lr_n + 1.0
    n = lr_n + Q_PRIOR_N       # Q_PRIOR_N pseudo-windows at log r = prior_at ("the HLM is not clearly better")
    mean = (lr_sum + Q_PRIOR_N * prior_at) / n
    var = (Q_V0 + max(lr_ss + Q_PRIOR_N * prior_at * prior_at - n * mean * mean, 0.0)) / (1.0 + n)
    lq = mean + Q_Z * math.sqrt(var / n)
    if SHADOW_REVOKE > 0 and r > max(math.log(SHADOW_REVOKE), Q_EDGES[-1]):
        lq = max(lq, r)   # a window that finds the HLM worse revokes its share at once
    return lr_sum, lr_ss, lr_n, lq


def _pair(name: str, v: Any, most: int = 2) -> tuple[Any, ...]:
    """A model file's (k, q[, q]) setting as its values (a clear error for anything else)."""
    if not isinstance(v, list | tuple) or not 2 <= len(v) <= most:
        raise FillerError(f"{METHOD}: {name} must be (k frames, q bound{', q bound' if most > 2 else ''}) (got {v!r})")
    return tuple(v)


def _gate_meta(g: tuple[Any, ...]) -> list[Any]:
    """long_gate as a model file writes it: (k, qlong), + qrev where it or rest is set, + rest where set
    (files of rounds 1-2 keep their two or three values)."""
    k, ql, qr, rest = (tuple(g) + (0.0, 0))[:4]
    return [int(k), float(ql)] + ([float(qr)] if qr > 0 or rest > 0 else []) + ([int(rest)] if rest > 0 else [])


def _check_long(name: str, k: Any, q: Any) -> tuple[int, float]:
    bad = any(isinstance(x, bool) or not isinstance(x, int | float) for x in (k, q))
    if bad or not math.isfinite(k) or not math.isfinite(q) or k < 0 or k != int(k) or (k > 0 and q <= 0):
        raise FillerError(f"{METHOD}: {name} must be (k >= 0 whole frames, q > 0) (got {(k, q)!r})")
    return int(k), float(q)


def _fork_stream(model: Model, hs: FillerState, into: FillerState | None) -> FillerState:
    """A copy of the HLM stream ``hs`` (its state pool's row copied into ``into``'s, or a new stream's)."""
    from mocap.feature_model import FeatureStream

    if type(hs) is FeatureStream and hs.model is model:
        c = into if type(into) is FeatureStream and into.model is model else model.stream()
        pool = model.pool   # type: ignore[attr-defined]
        for store in (pool.core, pool.repr):
            for v in store.values():
                v[c.slot] = v[hs.slot]   # type: ignore[attr-defined]
        return c
    return copy.deepcopy(hs, {id(model): model})


def _median_rate(num: np.ndarray, den: np.ndarray, ref: np.ndarray, ok: np.ndarray) -> float:
    """withhlm_fast._obs_median's: the median of num / den / ref where ``ok`` and den >= 1; -1 where none."""
    sel = ok & (den >= 1.0)
    return float(np.median(num[sel] / den[sel] / ref[sel])) if sel.any() else -1.0


def _ready(a: Any, dtype: Any, shape: tuple[int, ...]) -> bool:
    """``a`` is already what checked_batch would make of it: an ndarray of this dtype and shape,
    C-contiguous (then it is used as given, as checked_batch's ascontiguousarray would)."""
    return type(a) is np.ndarray and a.dtype == dtype and a.shape == shape and a.flags.c_contiguous


def _copy_state(s: FillerState) -> FillerState:
    """A stream's state with its own copies of every array (the model it refers to is shared)."""
    c = object.__new__(type(s))
    c.__dict__.update({k: v.copy() if isinstance(v, np.ndarray) else v for k, v in vars(s).items()})
    return c


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
    d = train_default(seqs, ch, names, fps=options.get("fps") or getattr(training_set, "fps", None),
                      skeleton=options.get("skeleton") or getattr(training_set, "skeleton", None))
    hopts = {k: v for k, v in options.items() if k not in ("fps", "skeleton")}
    # The HLM expert fills without hlm.condfill's correction unless told: on VALIDATION (the tuning
    # collection of bench/default_hlm_tune.py, W/S refitted for it) the mix scored 0.751 with it
    # against 0.742 without (pan2009 pattern 2.66 vs 2.36, runs 6.81 vs 7.11), and it costs the
    # HLM's step 1.3-1.5x (bench/notebook/hlmq-4.md); `lacuna train hlm` keeps it on.
    hopts.setdefault("cond_shrink", 0.0)
    h = train_hlm([seqs[i] for i in loco], ch, [names[i] for i in loco], **hopts)
    W0, S0, chosen = shipped()
    tau = float(chosen.get("tau", ANCHOR_TAU))
    meta = {"training": {"default": names, "hlm": [names[i] for i in loco],
                         "seconds": round(time.perf_counter() - t0, 2)},
            "weights": {"shipped": SHIPPED.name, **chosen} if W is None else {"given": True}}
    if LONG_TRUST[0] > 0:
        meta["long_trust"] = list(LONG_TRUST)
    if LONG_GATE[0] > 0:
        meta["long_gate"] = _gate_meta(LONG_GATE)
    if LONG_LL[0] > 0:
        meta["long_ll"] = list(LONG_LL)
        if LONG_LL_LEGS:
            meta["long_ll_legs"] = True
    cal = calib.from_json(json.loads(SHIPPED.read_text()).get("calib") if SHIPPED.exists() else None, list(ch),
                          group_index(list(ch)), GROUP_NAMES, len(T_EDGES) + 1)
    return WithHLMModel(d, h, W0 if W is None else W, S0 if S is None else S, meta, tau, cal,
                        chosen.get("smooth", SMOOTH), rate_ref(seqs, list(ch)), *shipped_band_q())


def shipped_band_q() -> tuple[np.ndarray | None, list[float] | None]:
    """(band_q, band_gate) from blend/withhlm.json ("band_q": {"M": G x Q, "gate": [r0, r1] or null});
    (None, None), i.e. off, where it has none."""
    if not SHIPPED.exists():
        return None, None
    bq = json.loads(SHIPPED.read_text()).get("band_q")
    if not bq:
        return None, None
    return np.array(bq["M"], float), bq.get("gate")


def rate_ref(sequences: list[np.ndarray], channels: list[str]) -> np.ndarray:
    """Each channel's mean |dx| a frame (wrapped for angles) over the consecutive frames of the
    training sequences where both are finite: the reference of the band's rate (module doc, "Rate");
    0 for a channel with no such pair."""
    ang = np.array([is_angle(c) for c in channels])
    tot, n = np.zeros(len(channels)), np.zeros(len(channels))
    for x in sequences:
        x = np.asarray(x, dtype=float)
        if len(x) < 2:
            continue
        ok = np.isfinite(x[1:]) & np.isfinite(x[:-1])
        d = np.where(ok, x[1:], 0.0) - np.where(ok, x[:-1], 0.0)
        d = np.abs(np.where(ang, wrap(d), d))
        tot += np.where(ok, d, 0.0).sum(0)
        n += ok.sum(0)
    return np.divide(tot, n, out=np.zeros(len(channels)), where=n > 0)
