#!/bin/bash
# alternated whole-run profiles, main then branch, NUMBA_NUM_THREADS=${T:-1}
S=/tmp/s7q/peers/peers_work/street_d1_s0/scan.npz
for i in $(seq 1 ${N:-1}); do
for side in main br; do
  src=/tmp/s16l/main_src; [ $side = br ] && src=/work/wt-16l
  cd $src; rm -rf /tmp/s16l/prun_$side
  NUMBA_NUM_THREADS=${T:-1} PYTHONPATH=$src /work/main/.venv/bin/python $src/scripts/profile_run.py --json /tmp/s16l/prun_${side}_T${T:-1}_$i.json -- run $S --out /tmp/s16l/prun_$side -q > /tmp/s16l/prun_${side}_T${T:-1}_$i.log 2>&1
  echo "$side $i done $(uptime)"
done; done
