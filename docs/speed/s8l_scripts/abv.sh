#!/bin/bash
n=$1
for i in $(seq 1 $n); do
  for side in main br; do
    src=/tmp/s16l/main_src; [ $side = br ] && src=/work/wt-16l
    cd $src
    NUMBA_NUM_THREADS=${T:-1} PYTHONPATH=$src /work/main/.venv/bin/python /tmp/s16l/vtime.py /tmp/s16l/street_map /tmp/s16l/street_ref.npz /tmp/s16l/street_lat.npz | sed "s/^/$side $i T${T:-1} /"
  done
done
