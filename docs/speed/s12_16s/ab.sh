#!/bin/bash
# alternated A/B of gmmgp run: main vs branch
out=/tmp/speed-16s/ab/$1; mkdir -p $out; n=${2:-3}
for r in $(seq 1 $n); do
  for side in main wt-16s; do
    d=$out/${side}_$r
    uptime > $d.load
    /usr/bin/time -f "%U %S %e %M" -o $d.time env PYTHONPATH=/work/$side /work/main/.venv/bin/python -m gmmgp_app.cli run /tmp/st11/scan.npz --out $d -q
    sha256sum $d/mesh_gmmgp.ply | cut -c1-16 > $d.sha
    rm -rf $d/map
  done
done
echo finished > $out/DONE
