#!/bin/bash
S=/tmp/st16w/scan.npz
cd /work/wt-16w
for r in $(seq 1 $1); do
  for mm in ${@:2}; do
    L=$(cat /proc/loadavg | cut -d' ' -f1)
    PYTHONPATH=$PWD /usr/bin/time -f "mm=$mm run$r maxrss_kb=%M wall=%e user=%U sys=%S minflt=%R load=$L" /work/main/.venv/bin/python /tmp/w16w/run_mm.py $mm run $S --out /tmp/w16w/ab_mm$mm -q 2>&1 | tail -1
  done
done
