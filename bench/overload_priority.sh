#!/usr/bin/env bash
# 4x overload (64 streams at 480 Hz, budget 4 ms) against a daemon started on its own, with the
# load generator at the same priority as the daemon and at nice 10 (as if the capture system ran
# on other cores or another machine), alternating, REPEATS times each.
#
#     bash bench/overload_priority.sh bench/out/hlm.npz 3 bench/out/overload-priority
#
# Writes OUT/{same,niced}-N.json (lacuna bench JSON) and prints one line per run.
set -euo pipefail
MODEL=$(realpath "${1:?model file}")
REPEATS=${2:-3}
OUT=${3:-bench/out/overload-priority}
PORT=${PORT:-5591}
LACUNA=${LACUNA:-$(command -v lacuna || echo .venv/bin/lacuna)}
mkdir -p "$OUT"
cat > "$OUT/lacuna.toml" <<TOML
[daemon]
budget_ms = 4.0
default_model = "bench"
log_level = "warning"

[models.bench]
file = "$MODEL"

[zmq]
router = "tcp://127.0.0.1:$PORT"
TOML
export OPENBLAS_NUM_THREADS=1
for r in $(seq 0 $((REPEATS - 1))); do
  for mode in same niced; do
    "$LACUNA" serve --config "$OUT/lacuna.toml" 2> "$OUT/daemon-$mode-$r.log" &
    D=$!
    for _ in $(seq 100); do grep -q '"ready"' "$OUT/daemon-$mode-$r.log" 2>/dev/null && break; sleep 0.1; done
    if [ "$mode" = niced ]; then N="nice -n 10"; else N=""; fi
    $N "$LACUNA" bench --connect "tcp://127.0.0.1:$PORT" --streams 64 --rate 480 --seconds 6 -q \
      --json "$OUT/$mode-$r.json" > "$OUT/$mode-$r.txt" 2>&1
    kill -TERM $D; wait $D || true
    python3 - "$OUT/$mode-$r.json" "$mode" "$r" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print(f"{sys.argv[2]:5s} run {sys.argv[3]}: served {d['served']}, degraded {d['degraded']}, conflated {d['dropped']}, lost {d['lost']}, "
      f"round trip p50/p99 {d['p50_ms']:.1f}/{d['p99_ms']:.1f} ms, receipt-to-reply p50/p99 {d['daemon_proc_ms_p50']:.2f}/"
      f"{d['daemon_proc_ms_p99']:.2f} ms, served over budget {d['daemon_over_budget_pct']:.1f}%")
PY
  done
done
