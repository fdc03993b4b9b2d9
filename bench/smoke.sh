#!/usr/bin/env bash
# Every script of bench/ and examples/ run once, on the smallest settings that take it from its
# start to its end: a check that each still runs against today's code, not a benchmark. Two of
# them had stopped running unnoticed after changes elsewhere (bench/RESULTS.md, "2026-12-02, night").
#
#   bash bench/smoke.sh [WORKDIR]      # `make bench-smoke`; .ci/run runs it after `make test`
#
# The programs compile as the test suite's do (XLA level 0, tests/conftest.py), with a compilation
# cache of their own in WORKDIR: the figures the scripts print here mean nothing. Prints one line
# per script and exits 1 if any failed, with the end of its log; without WORKDIR it works in a new
# temporary folder, removed when every script ran. Skipped, and said so:
# examples/sb3_ppo.py (stable-baselines3 and torch are not d2spo's dependencies) and the full runs
# (bench/fingerprint.sh compares two trees; bench/gpu.sh runs its QUICK=1 check here).
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
W=${1:-}
own=0
[ -z "$W" ] && { W=$(mktemp -d "${TMPDIR:-/tmp}/d2spo-bench-smoke.XXXXXX"); own=1; }
mkdir -p "$W"
export XLA_FLAGS="${XLA_FLAGS:-} --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
export D2SPO_XLA_LONG_RUNNING_LEVEL=${D2SPO_XLA_LONG_RUNNING_LEVEL:-2}  # D²SPO's pre-training runs long
export D2SPO_COMPILE_CACHE="$W/cache" MPLBACKEND=Agg
D2SPO="$PY -m d2spo.cli"
failed=0
begin=$SECONDS

check() {  # check NAME COMMAND...: run it, its output in WORKDIR/NAME.log
  local name=$1 start=$SECONDS
  shift
  if timeout 900 "$@" >"$W/$name.log" 2>&1; then
    printf 'ok      %-24s %4d s\n' "$name" $((SECONDS - start))
  else
    printf 'FAILED  %-24s %4d s  (exit %d; %s)\n' "$name" $((SECONDS - start)) "$?" "$W/$name.log"
    tail -n 8 "$W/$name.log" | sed 's/^/        /'
    failed=1
  fi
}

echo "bench smoke in $W"
# the runs the scripts read: a specialist, a patrol, a generalist with snapshots and a validation
check train-specialist $D2SPO train --task phi1 --layout paper --episodes 32 --eval-episodes 4 --no-progress --out "$W/run"
check train-patrol $D2SPO train --task patrol2 --layout paper --episodes 16 --eval-episodes 2 --no-progress --out "$W/patrol"
check train-generalist $D2SPO train --algo d2spo --generalist --task phi1 --episodes 64 --generalist-layouts 4 \
  --validation-layouts 1 --validation-episodes 2 --snapshots 32 64 --eval-episodes 0 --no-progress --out "$W/gen"

check barrier_margin $PY bench/barrier_margin.py --tasks phi1 --layouts paper --halvings 2
check buchi_exactness $PY bench/buchi_exactness.py --formulas 5 --words 10
check buchi_times $PY bench/buchi_times.py
check route_bound $PY bench/route_bound.py --margins 0.25
check gymnax_loop $PY bench/gymnax_loop.py --steps 20
check compile_threads $PY bench/compile_threads.py
check concurrency $PY bench/concurrency.py --hidden 16 --batch 16 --steps 50
check machine_speed $PY bench/machine_speed.py --repeats 1
check layout_fields $PY bench/layout_fields.py --layouts 2 --chunk 2 --bank 0
check env_throughput $PY bench/env_throughput.py --sizes 1,64 --repeats 1
check compile_times $PY bench/compile_times.py --fast --no-pretrain
check profile_chunk $PY bench/profile_chunk.py --steps 10 --repeats 1
check td3_flops $PY bench/td3_flops.py --repeats 1 --updates 20 --hidden 32 32 --batch 32
check train_throughput $PY bench/train_throughput.py --algos tlgrl ppo-lag sac-lag --chunks 1 --td3-hidden 32 32 \
  --td3-batch 32 --learning-starts 0
check vmap_seeds $PY bench/vmap_seeds.py --algos ppo-lag --seeds 2 --chunks 1
check cautious_start $PY bench/cautious_start.py --episodes 4 --seeds 0
check task_suite $PY bench/task_suite.py --episodes 16 --tasks phi1 --eval-episodes 2 --out "$W/suite" --results -
check patrol_laps $PY bench/patrol_laps.py "$W/patrol" --episodes 2 --margins 0.25 --plot "$W/laps.png"
check generalist_stalls $PY bench/generalist_stalls.py "$W/gen" --layouts 1 --episodes 1 --policy last --probe
check buchi_zero_shot $PY bench/buchi_zero_shot.py --runs "$W/gen" --tasks patrol2 reach-never --layouts 1 \
  --episodes 2 --max-steps 100 --results - --handmade --cases 3
check policy_average $PY bench/policy_average.py --run "$W/gen" --windows 64 --out "$W/average.jsonl" \
  --keep-as "$W/average.msgpack"
check generalisation $PY bench/generalisation.py --run "$W/gen" --specialist "$W/run" --layouts 1 --tasks phi1 \
  --episodes 2 --own-episodes 2 --trajectories 1 --out "$W/generalisation" --results -
check handmade $PY bench/handmade.py --run "$W/gen" --episodes 2 --policy last --cases 3 --out "$W/handmade"
check zones $PY bench/zones.py --quick --runs "$W/zones-runs" --out "$W/zones"
check fault_battery $PY bench/fault_battery.py --only 1 --quick --out "$W/battery.md"
check suite_profile env PYTHONPATH=bench D2SPO_SUITE_PROFILE="$W/suite-profile" D2SPO_TEST_JAX_CACHE="$W/test-cache" \
  $PY -m pytest -q -p no:cacheprovider -p suite_profile tests/test_common_gae.py
check suite_profile_report $PY bench/suite_profile.py "$W/suite-profile" --top 5
check compile_count env PYTHONPATH=bench D2SPO_TEST_JAX_CACHE="$W/test-cache" \
  $PY -m pytest -q -p no:cacheprovider -p compile_count tests/test_common_gae.py
check gpu_quick env QUICK=1 PY="$PY" bash bench/gpu.sh "$W/gpu"
check deploy_gym_loop $PY examples/deploy_gym_loop.py "$W/run" --episodes 1
check deploy_match $PY bench/deploy_match.py "$W/run" --episodes 1 --policy last
echo "skipped examples/sb3_ppo.py (needs stable-baselines3 and torch), bench/fingerprint.sh (compares two trees)"
echo "bench smoke: $((SECONDS - begin)) s, $([ $failed = 0 ] && echo 'every script ran' || echo 'FAILED')"
# a folder of its own making goes once every script ran (about 1.1 GB: runs and compiled programs)
[ $failed = 0 ] && [ $own = 1 ] && rm -rf "$W"
exit $failed
