#!/bin/bash
# usage: bench/fingerprint.sh SRC_ROOT OUTDIR
# Trains each of the 9 learners for 48 episodes (seed 0), evaluates d2spo, and writes OUTDIR/FINGERPRINT:
# per learner the SHA-256 (16 hex) of episodes.csv, of its checkpoints and of summary.json without
# timings. Two source trees give the same lines iff their results are byte-identical (the eval text
# line also holds the output path). Used to check refactors (issue 13).
set -e
SRC=$1; OUT=$2; mkdir -p $OUT
PY=${PY:-$(cd "$(dirname "$0")/.." && pwd)/.venv/bin/python}
for algo in ${ALGOS:-d2spo td3 tlgrl sl td3-lag sac-lag rcrl ppo-lag cpo}; do
  rm -rf $OUT/$algo
  N=8; C=100; case $algo in ppo-lag|cpo) N=16; C=250;; esac
  PYTHONPATH=$SRC/src $PY -m d2spo.cli train --algo $algo --episodes 48 --num-envs $N --chunk-steps $C --eval-episodes 8 --checkpoint-every 24 --no-progress --out $OUT/$algo > $OUT/$algo.log 2>&1 || echo "FAIL $algo"
done
PYTHONPATH=$SRC/src $PY -m d2spo.cli eval $OUT/d2spo --episodes 8 > $OUT/eval-d2spo.txt 2>&1 || echo "FAIL eval"
cd $OUT && for algo in d2spo td3 tlgrl sl td3-lag sac-lag rcrl ppo-lag cpo; do
  echo "$algo $(sha256sum $algo/episodes.csv | cut -c1-16) $(cat $algo/checkpoint-*.msgpack 2>/dev/null | sha256sum | cut -c1-16) $(python3 -c "import json;d=json.load(open('$algo/summary.json'));d={k:v for k,v in d.items() if 'second' not in k and 'wall' not in k};print(json.dumps(d,sort_keys=True))" | sha256sum | cut -c1-16)"
done > $OUT/FINGERPRINT
grep -v -i "second\|wall\| s\b" $OUT/eval-d2spo.txt | sha256sum | cut -c1-16 >> $OUT/FINGERPRINT
cat $OUT/FINGERPRINT
