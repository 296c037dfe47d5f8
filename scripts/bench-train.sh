#!/usr/bin/env bash
# Time-to-laps benchmark: train from scratch with several seeds until an evaluation completes
# 3 of 3 laps; print a markdown table. Usage: scripts/bench-train.sh WORLD [SEEDS]
set -euo pipefail
cd "$(dirname "$0")/.."
world=${1:-reinvent_base}
seeds=${2:-5}
bin=target/release/coordinator
[ -x "$bin" ] || cargo build --release -q -p coordinator
tmp=$(mktemp -d)
echo "| world | seed | wall-clock s | iterations | episodes | env steps | eval laps | mean lap s |"
echo "|---|---|---|---|---|---|---|---|"
for seed in $(seq 1 "$seeds"); do
  out="$tmp/run-$seed"
  start=$(date +%s.%N)
  "$bin" train --world "$world" --seed "$seed" --minutes 10 --out "$out" >/dev/null 2>&1
  end=$(date +%s.%N)
  python3 - "$out/summary.json" "$world" "$seed" "$start" "$end" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
b = s.get("best") or {}
laps = "3/3" if s["stop_reason"].startswith("target laps reached") else "not reached"
lap = b.get("avg_lap_time")
print(f"| {sys.argv[2]} | {sys.argv[3]} | {float(sys.argv[5]) - float(sys.argv[4]):.1f} | {s['iterations']} | {s['episodes']} | {s['env_steps']} | {laps} | {lap:.2f} |" if lap else
      f"| {sys.argv[2]} | {sys.argv[3]} | {float(sys.argv[5]) - float(sys.argv[4]):.1f} | {s['iterations']} | {s['episodes']} | {s['env_steps']} | {laps} | - |")
PY
done
rm -rf "$tmp"
