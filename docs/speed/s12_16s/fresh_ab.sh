#!/bin/bash
for r in $(seq 1 $2); do for side in main wt-16s; do uptime | sed 's/.*average: //' | tr '\n' ' '; PYTHONPATH=/work/$side /work/main/.venv/bin/python /tmp/speed-16s/freshrun.py $side 2>&1 | tail -1; done; done > /tmp/speed-16s/$1.log
echo DONE >> /tmp/speed-16s/$1.log
