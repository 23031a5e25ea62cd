#!/bin/bash
# alternated whole `gmmgp run` on the street: main vs wt-16a; $1 tag, $2 pairs
out=/tmp/speed-16a/runab/$1; mkdir -p $out
for r in $(seq 1 $2); do
  for side in main wt-16a; do
    d=/tmp/speed-16a/runs/$side; rm -rf $d
    load=$(cut -d' ' -f1 /proc/loadavg)
    cd /work/$side && /usr/bin/time -f "%e %U %S %M" -o $out/${side}_$r.time env PYTHONPATH=/work/$side /work/main/.venv/bin/gmmgp run /tmp/st11/scan.npz --out $d -q > /dev/null 2>&1
    python3 -c "
import json,sys; s=json.load(open('$d/summary.json'))['seconds']; t=open('$out/${side}_$r.time').read().split()
print('$side', $r, 'load', $load, 'wall', t[0], 'cpu', round(float(t[1])+float(t[2]),2), 'rss', int(t[3])//1024, 'surface', round(s['surface'],2), 'total', round(s['total'],2))" >> $out/log
    sha256sum $d/mesh_gmmgp.ply | cut -c1-16 >> $out/sha
  done
done
echo finished > $out/DONE
