#!/bin/bash
# gmmgp run on the three scans with main and the branch; mesh SHA-256 and summary seconds
O=/tmp/speed-16k/runs; mkdir -p $O; uptime > $O/uptime_start.txt
for r in 1 2; do
for c in kitti:/tmp/speed-16p/kitti.npz street10:/tmp/speed-16p/street10.npz street:/tmp/st11/scan.npz; do
  n=${c%%:*}; f=${c#*:}
  for t in main wt; do
    if [ $t = main ]; then P=/work/main; else P=/work/wt-16k; fi
    rm -rf $O/${t}_$n
    /usr/bin/time -f "%e wall %U user %S sys %M KB" -o $O/${t}_${n}_$r.time env PYTHONPATH=$P /work/main/.venv/bin/python -m gmmgp_app.cli run $f --out $O/${t}_$n -q > /dev/null 2>&1
    echo "$t $n $r $(sha256sum $O/${t}_$n/mesh_gmmgp.ply | cut -c1-16) $(cat $O/${t}_${n}_$r.time) surface $(python3 -c "import json;d=json.load(open('$O/${t}_$n/summary.json'));s=d.get('seconds',d);print(s.get('surface'))" 2>/dev/null)" >> $O/sha.txt
  done
done
done
uptime > $O/uptime_end.txt
