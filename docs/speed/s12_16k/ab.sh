#!/bin/bash
# usage: ab.sh TAG REPS ENV_ASSIGN SERIALFLAG  -> /tmp/speed-16k/ab/TAG/{main,wt}_{case}_{rep}.json
TAG=$1; REPS=$2; ENVA=$3; SER=$4
O=/tmp/speed-16k/ab/$TAG; mkdir -p $O
uptime > $O/uptime_start.txt
for r in $(seq 1 $REPS); do
 for c in kitti street10 street; do
  for t in main wt; do
   if [ $t = main ]; then P=/work/main; else P=/work/wt-16k; fi
   env $ENVA PYTHONPATH=$P /work/main/.venv/bin/python /work/wt-16k/scripts/profile_surface.py /tmp/speed-16k/map_$c/map $SER --compare /tmp/speed-16k/ref_$c.npz --json $O/${t}_${c}_$r.json > $O/${t}_${c}_$r.log 2>&1
  done
 done
done
uptime > $O/uptime_end.txt
