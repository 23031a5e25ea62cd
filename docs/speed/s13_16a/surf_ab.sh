#!/bin/bash
# alternated surface-only A/B on the saved map; $1 tag, $2 reps, $3 extra env (e.g. NUMBA_NUM_THREADS=1), $4 extra args
out=/tmp/speed-16a/sab/$1; mkdir -p $out
for r in $(seq 1 $2); do
  for side in main wt-16a; do
    cd /work/$side && env $3 PYTHONPATH=/work/$side /work/main/.venv/bin/python scripts/profile_surface.py ${MAP:-/tmp/speed-16a/base/map} --repeat 2 $4 --json $out/${side}_$r.json > /dev/null 2>&1
  done
done
echo finished > $out/DONE
