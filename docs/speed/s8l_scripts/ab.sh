#!/bin/bash
# ab.sh SCENE N: alternated main / branch surface extractions (second in the process), NUMBA_NUM_THREADS=${T:-1}
scene=$1; n=$2
for i in $(seq 1 $n); do
  for side in main br; do
    src=/tmp/s16l/main_src; [ $side = br ] && src=/work/wt-16l
    cd $src
    if [ $side = main ]; then out=/tmp/s16l/${scene}_ref.npz; cmp=""; else out=/tmp/s16l/${scene}_br.npz; cmp=/tmp/s16l/${scene}_ref.npz; fi
    NUMBA_NUM_THREADS=${T:-1} PYTHONPATH=$src /work/main/.venv/bin/python /tmp/s16l/mesh.py /tmp/s16l/${scene}_map $out 2 $cmp | sed "s/^/$side $scene $i T${T:-1} /"
  done
done
