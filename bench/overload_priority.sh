#!/usr/bin/env bash
# 4x overload (64 streams at 480 Hz, budget 4 ms) against a daemon started on its own, in up to
# four set-ups, alternating, REPEATS times each:
#   same      the load generator at the daemon's priority (both ordinary)
#   niced     the load generator at nice 10 (as if the capture system ran on other cores or another
#             machine)
#   realtime  the daemon's serving threads at SCHED_RR 10 (daemon.realtime_priority; needs root or
#             RLIMIT_RTPRIO), the load generator ordinary
#   rt-serve  realtime, with daemon.overdue = "serve": frames the daemon cannot answer in budget
#             are served late instead of dropped (what the drop is worth)
#
#     bash bench/overload_priority.sh bench/out/hlm.npz 3 bench/out/overload-priority [MODES]
#
# MODES defaults to "same niced realtime rt-serve".  Writes OUT/{mode}-N.json (lacuna bench JSON)
# and prints one line per run.
set -euo pipefail
MODEL=$(realpath "${1:?model file}")
REPEATS=${2:-3}
OUT=${3:-bench/out/overload-priority}
MODES=${4:-same niced realtime rt-serve}
PORT=${PORT:-5591}
LACUNA=${LACUNA:-$(command -v lacuna || echo .venv/bin/lacuna)}
mkdir -p "$OUT"
config() {  # $1 = extra [daemon] lines
  cat <<TOML
[daemon]
budget_ms = 4.0
default_model = "bench"
log_level = "warning"
$1

[models.bench]
file = "$MODEL"

[zmq]
router = "tcp://127.0.0.1:$PORT"
TOML
}
export OPENBLAS_NUM_THREADS=1
for r in $(seq 0 $((REPEATS - 1))); do
  for mode in $MODES; do
    case $mode in
      same|niced) config "" > "$OUT/lacuna-$mode.toml" ;;
      realtime) config "realtime_priority = 10" > "$OUT/lacuna-$mode.toml" ;;
      rt-serve) config $'realtime_priority = 10\noverdue = "serve"' > "$OUT/lacuna-$mode.toml" ;;
      *) echo "unknown mode $mode" >&2; exit 2 ;;
    esac
    "$LACUNA" serve --config "$OUT/lacuna-$mode.toml" 2> "$OUT/daemon-$mode-$r.log" &
    D=$!
    for _ in $(seq 100); do grep -q '"ready"' "$OUT/daemon-$mode-$r.log" 2>/dev/null && break; sleep 0.1; done
    if grep -q '"realtime_refused"' "$OUT/daemon-$mode-$r.log"; then
      echo "$mode: the daemon could not get SCHED_RR (see $OUT/daemon-$mode-$r.log); run as root or raise RLIMIT_RTPRIO" >&2
    fi
    if [ "$mode" = niced ]; then N="nice -n 10"; else N=""; fi
    $N "$LACUNA" bench --connect "tcp://127.0.0.1:$PORT" --streams 64 --rate 480 --seconds 6 -q \
      --json "$OUT/$mode-$r.json" > "$OUT/$mode-$r.txt" 2>&1
    kill -TERM $D; wait $D || true
    python3 - "$OUT/$mode-$r.json" "$mode" "$r" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
rt = (d.get("realtime") or {}).get("held")
print(f"{sys.argv[2]:8s} run {sys.argv[3]}: served {d['served']}, degraded {d['degraded']}, "
      f"conflated {d['drop_reasons'].get('conflated', 0)}, overdue {d['drop_reasons'].get('overdue', 0)}, lost {d['lost']}, "
      f"round trip p50/p99 {d['p50_ms']:.1f}/{d['p99_ms']:.1f} ms, receipt-to-encoding p50/p99 {d['daemon_proc_ms_p50']:.2f}/"
      f"{d['daemon_proc_ms_p99']:.2f} ms, served over budget (receipt to sent) {d['daemon_over_budget_pct']:.2f}%, "
      f"SCHED_RR {'held' if rt else 'no'}, counts agree {d['counts_agree']}")
PY
  done
done
