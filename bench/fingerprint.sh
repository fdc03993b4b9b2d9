#!/bin/bash
# usage: bench/fingerprint.sh SRC_ROOT OUTDIR
# Trains each of the 9 learners and a small generalist for 48 episodes (seed 0), evaluates d2spo on its
# layout and the generalist zero-shot on another task and three unseen layouts, and writes OUTDIR/FINGERPRINT:
# per learner the SHA-256 (16 hex) of episodes.csv, of its checkpoints and of summary.json without
# timings, and of the evaluations' printouts and JSON files (without timings, progress clocks and output paths; give
# OUTDIRs of the same length, as the printout's centred title holds the path). Two source trees
# give the same lines iff their results are byte-identical. Used to check refactors.
set -e
SRC=$1; OUT=$2; mkdir -p $OUT
PY=${PY:-$(cd "$(dirname "$0")/.." && pwd)/.venv/bin/python}
if [ -z "$HASH_ONLY" ]; then  # HASH_ONLY=1: only hash the runs already in OUTDIR
for algo in ${ALGOS:-d2spo td3 tlgrl sl td3-lag sac-lag rcrl ppo-lag cpo}; do
  rm -rf $OUT/$algo
  N=8; C=100; case $algo in ppo-lag|cpo) N=16; C=250;; esac
  PYTHONPATH=$SRC/src $PY -m d2spo.cli train --algo $algo --episodes 48 --num-envs $N --chunk-steps $C --eval-episodes 8 --checkpoint-every 24 --no-progress --out $OUT/$algo > $OUT/$algo.log 2>&1 || echo "FAIL $algo"
done
PYTHONPATH=$SRC/src $PY -m d2spo.cli eval $OUT/d2spo --episodes 8 > $OUT/eval-d2spo.txt 2>&1 || echo "FAIL eval"
# a small generalist, and its zero-shot eval on another task over three unseen layouts
rm -rf $OUT/generalist
PYTHONPATH=$SRC/src $PY -m d2spo.cli train --algo d2spo --generalist --generalist-layouts 4 --validation-layouts 2 \
  --validation-episodes 4 --validate-every 24 --episodes 48 --num-envs 8 --chunk-steps 100 --eval-episodes 8 \
  --checkpoint-every 24 --no-progress --out $OUT/generalist > $OUT/generalist.log 2>&1 || echo "FAIL generalist"
PYTHONPATH=$SRC/src $PY -m d2spo.cli eval $OUT/generalist --task "F A2" --layout random:300 --layout-seeds 3 \
  --episodes 8 > $OUT/eval-generalist.txt 2>&1 || echo "FAIL zero-shot eval"
fi
cd $OUT && for algo in d2spo td3 tlgrl sl td3-lag sac-lag rcrl ppo-lag cpo generalist; do
  echo "$algo $(sha256sum $algo/episodes.csv | cut -c1-16) $(cat $algo/checkpoint-*.msgpack 2>/dev/null | sha256sum | cut -c1-16) $(python3 -c "import json
def clean(d):
    if isinstance(d, dict): return {k: clean(v) for k, v in d.items() if 'second' not in k and 'wall' not in k}
    return [clean(v) for v in d] if isinstance(d, list) else d
print(json.dumps(clean(json.load(open('$algo/summary.json'))), sort_keys=True))" | sha256sum | cut -c1-16)"
done > $OUT/FINGERPRINT
for e in d2spo generalist; do  # the eval's printout and its JSON file, without timings
  echo "eval-$e $(grep -v -i "second\|wall\| s\b\|wrote" eval-$e.txt | sed -E "s#$OUT##g; s/[0-9]+:[0-9]{2}:[0-9]{2}//g" | tr -s ' ' | sha256sum | cut -c1-16) $(python3 -c "import json,glob
d=[json.load(open(p)) for p in sorted(glob.glob('$e/eval-*.json'))]
print(json.dumps([{k: v for k, v in x.items() if 'second' not in k and 'wall' not in k and k != 'run'} for x in d], sort_keys=True))" | sha256sum | cut -c1-16)"
done >> $OUT/FINGERPRINT
cat $OUT/FINGERPRINT
