#!/usr/bin/env bash
# One stream at 120 Hz through `lacuna bench --model MODEL --floor`, with the daemon's prewarm at
# each lead of LEADS (0 = off), alternating run by run so a busy spell of the shared machine falls
# on every lead, REPEATS times, once with the daemon at SCHED_RR 10 and once ordinary; the CPUs are
# kept out of sleep states (--cpu-latency 0) in both.  Prints a markdown table: per lead, the
# medians over the repeats of the round trip's p50 and p99 (range of p99) and of the daemon's own
# receipt-to-encoding p50 / p99, for the model and the pass-through floor of the same runs, and
# for the model how many of its frames found a rehearsal before them (rehearsals / frames sent)
# and the period the daemon measured (ms; 8.333 at 120 Hz) -- figures tests/test_daemon_prewarm.py
# used to assert (at least half rehearsed, period within 0.7-1.5x) and now leaves to this script.
#
#     bash bench/prewarm_ab.sh bench/out/hlm.npz 4 bench/out/prewarm-ab "0 0.25 0.5 1"
# (run as this file 2026-11-23 08:31-08:41 UTC: docs/BENCHMARKS.md, bench/results/prewarm_ab_2026-11-23_0831.json)
set -euo pipefail
MODEL=$(realpath "${1:?model file}")
REPEATS=${2:-4}
OUT=${3:-bench/out/prewarm-ab}
LEADS=${4:-0 0.25 0.5 1}
LACUNA=${LACUNA:-$(command -v lacuna || echo .venv/bin/lacuna)}
PYTHON=${PYTHON:-$(dirname "$LACUNA")/python}
mkdir -p "$OUT"
export OPENBLAS_NUM_THREADS=1
for r in $(seq 0 $((REPEATS - 1))); do
  for cfg in rt sleep; do
    for pw in $LEADS; do
      if [ $cfg = rt ]; then X="--realtime 10"; else X=""; fi
      # shellcheck disable=SC2086
      "$LACUNA" bench --streams 1 --rate 120 --seconds 8 --model "$MODEL" --floor --cpu-latency 0 --prewarm "$pw" $X -q \
        --json "$OUT/$cfg-$pw-$r.json" > "$OUT/$cfg-$pw-$r.txt" 2>&1
      echo "$(date +%T) $cfg prewarm=$pw repeat $r: $(grep -E '^model' "$OUT/$cfg-$pw-$r.txt" | awk '{print "p50", $6, "p99", $8}')" >&2
    done
  done
done
"$PYTHON" - "$OUT" "$LEADS" <<'PY'
import glob, json, sys
import numpy as np
out, leads = sys.argv[1], sys.argv[2].split()
print("| daemon | prewarm_ms | runs | model p50 | model p99 (range) | model daemon p50 / p99 | floor p50 | floor p99 (range) | floor daemon p50 / p99 | rehearsed | period ms |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for cfg in ("rt", "sleep"):
    for pw in leads:
        rows, rehearsed, period = [], [], []
        for f in sorted(glob.glob(f"{out}/{cfg}-{pw}-*.json")):
            r = json.load(open(f))["runs"]
            rows.append([r[k][q] for k in ("model", "floor")
                         for q in ("p50_ms", "p99_ms", "daemon_proc_ms_p50", "daemon_proc_ms_p99")])
            p = r["model"].get("prewarm") or {}
            if r["model"].get("sent"):
                rehearsed.append(p.get("rehearsals", 0) / r["model"]["sent"])
            if p.get("period_ms") is not None:
                period.append(p["period_ms"])
        if not rows:
            continue
        a = np.array(rows)
        m = np.median(a, axis=0)
        print(f"| {'SCHED_RR 10' if cfg == 'rt' else 'ordinary'} | {pw} | {len(rows)} | {m[0]:.2f} | {m[1]:.2f} "
              f"({a[:, 1].min():.2f}-{a[:, 1].max():.2f}) | {m[2]:.3f} / {m[3]:.3f} | {m[4]:.2f} | {m[5]:.2f} "
              f"({a[:, 5].min():.2f}-{a[:, 5].max():.2f}) | {m[6]:.3f} / {m[7]:.3f} | "
              f"{f'{100 * np.median(rehearsed):.0f}%' if rehearsed else '-'} | "
              f"{f'{np.median(period):.3f}' if period else '-'} |")
PY
