#!/usr/bin/env bash
# The GPU figures of bench/RESULTS.md in one go (it runs on a CPU too, where it gives the CPU's):
#   env steps/s for 1 ... 16384 envs, D²SPO training steps/s, 3 vmapped seeds, the phi1 protocol.
#
#   bash bench/gpu.sh [OUT]          # OUT (default /tmp/d2spo-gpu) gets gpu.json, the logs and the phi1 run
#   PY=.venv/bin/python bash bench/gpu.sh
#   QUICK=1 bash bench/gpu.sh        # a minute-long check of the script itself: small sizes, 200 episodes
#   PHI1_LIMIT=300 bash bench/gpu.sh # stop the phi1 run after this many seconds (0: no limit, the default)
#   BUDGET=540 bash bench/gpu.sh     # the whole script within this many seconds: phi1 gets what is left
#                                    # (a stopped phi1 run reports the episodes it finished)
#
# On a CUDA machine install the CUDA build first: pip install 'd2spo[cuda]' (docs/runs.md, "On a GPU").
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
OUT=${1:-/tmp/d2spo-gpu}
QUICK=${QUICK:-0}
PHI1_LIMIT=${PHI1_LIMIT:-0}
BUDGET=${BUDGET:-0}
t0=$SECONDS
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1

if [ "$QUICK" = 1 ]; then
  sizes=1,64,1024; repeats=1; chunks=1; episodes=200
else
  sizes=1,64,1024,4096,16384; repeats=3; chunks=3; episodes=20000
fi

echo "== device"
"$PY" - <<'EOF' | tee "$OUT/device.txt"
import jax, platform
d = jax.devices()[0]
print(f"jax {jax.__version__}, backend {jax.default_backend()}, device {d.device_kind} ({d.platform}), "
      f"{jax.device_count()} device(s), python {platform.python_version()}")
EOF

echo "== env steps/s (bench/env_throughput.py --sizes $sizes)"
"$PY" bench/env_throughput.py --sizes "$sizes" --repeats "$repeats" | tee "$OUT/env.log"

echo "== D2SPO training (bench/train_throughput.py --algos d2spo --chunks $chunks)"
"$PY" bench/train_throughput.py --algos d2spo --chunks "$chunks" | tee "$OUT/train.log"

echo "== 3 seeds vmapped (bench/vmap_seeds.py --algos d2spo --seeds 3 --chunks $chunks)"
"$PY" bench/vmap_seeds.py --algos d2spo --seeds 3 --chunks "$chunks" | tee "$OUT/vmap.log"

if [ "$BUDGET" != 0 ]; then
  PHI1_LIMIT=$(( BUDGET - (SECONDS - t0) - 20 ))
  [ "$PHI1_LIMIT" -gt 30 ] || PHI1_LIMIT=30
fi
echo "== phi1 protocol: d2spo train --task phi1 --layout paper --episodes $episodes (limit ${PHI1_LIMIT}s, 0 = none)"
rm -rf "$OUT/phi1"
start=$(date +%s.%N)
status=0
lim=()
[ "$PHI1_LIMIT" != 0 ] && lim=(timeout -s INT "$PHI1_LIMIT")
# a log rather than a terminal: one plain progress line when compilation starts and ends, then every 30 s
"${lim[@]}" "$PY" -m d2spo.cli train --task phi1 --layout paper --episodes "$episodes" --out "$OUT/phi1" \
  2>&1 | tee "$OUT/phi1.log" || status=$?
end=$(date +%s.%N)

"$PY" - "$OUT" "$start" "$end" "$status" <<'EOF'
import json, sys
from pathlib import Path
out, start, end, status = Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
def last(name):
    try:
        return json.loads((out / name).read_text().strip().splitlines()[-1])
    except (OSError, IndexError, ValueError):
        return None
res = {"device": (out / "device.txt").read_text().strip(), "env_steps_per_s": last("env.log"),
       "train_env_steps_per_s": last("train.log"), "vmap": last("vmap.log")}
phi1 = {"seconds": round(end - start, 1), "exit_status": status}
summary = out / "phi1" / "summary.json"
if summary.is_file():
    s = json.loads(summary.read_text())
    phi1.update({k: s.get(k) for k in ("episodes", "env_steps", "compile_seconds", "wall_seconds",
                                       "env_steps_per_second", "safety_rate", "completion_rate", "eval")})
else:  # stopped at PHI1_LIMIT: how far it got
    csv = out / "phi1" / "episodes.csv"
    phi1["episodes_done"] = max(0, len(csv.read_text().splitlines()) - 1) if csv.is_file() else 0
res["phi1"] = phi1
(out / "gpu.json").write_text(json.dumps(res, indent=1))
print(json.dumps(res))
EOF
