#!/bin/bash
# alternated whole runs: main vs branch; $1 = label, $2 = n
S=/tmp/st16w/scan.npz
for r in $(seq 1 $2); do
  for t in main wt-16w; do
    cd /work/$t
    L=$(cat /proc/loadavg | cut -d' ' -f1)
    PYTHONPATH=$PWD /usr/bin/time -f "$t run$r maxrss_kb=%M wall=%e user=%U sys=%S minflt=%R load=$L" /work/main/.venv/bin/python -m gmmgp_app.cli run $S --out /tmp/w16w/ab_$t -q 2>&1 | tail -1
    sha256sum /tmp/w16w/ab_$t/mesh_gmmgp.ply | cut -c1-16
  done
done
