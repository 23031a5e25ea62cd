#!/bin/bash
S=/tmp/st16w/scan.npz
for r in $(seq 1 $1); do
  for cfg in main branch passive; do
    if [ $cfg = main ]; then T=/work/main; else T=/work/wt-16w; fi
    if [ $cfg = passive ]; then export OMP_WAIT_POLICY=PASSIVE; else unset OMP_WAIT_POLICY; fi
    cd $T
    L=$(cut -d' ' -f1 /proc/loadavg)
    PYTHONPATH=$T /usr/bin/time -f "$cfg run$r maxrss_kb=%M wall=%e user=%U sys=%S minflt=%R load=$L" /work/main/.venv/bin/python -m gmmgp_app.cli run $S --out /tmp/w16w/ab3_$cfg -q 2>&1 | tail -1
  done
done
unset OMP_WAIT_POLICY
sha256sum /tmp/w16w/ab3_*/mesh_gmmgp.ply | cut -c1-16
