#!/bin/bash
# Peak RSS, wall and CPU time of `scope3d map` on the 30-frame dome at several pose-noise levels, for two
# source trees (e.g. before and after a change), one run at a time. Results in
# benchmarks/results/map_pose_noise_memory.json came from:
#   git archive f2a4776 src | tar -x -C /tmp/before
#   for n in 0.25 1 3 5; do scope3d phantom dome --seed 41 --pose-noise $n --out /tmp/dome41_$n; done
#   BEFORE=/tmp/before/src AFTER=$PWD/src DATA=/tmp/dome41_ benchmarks/map_noise_memory.sh
# Each tree maps the first level once first, to warm its numba caches (compiled per source path).
PY=${PY:-.venv/bin/python}
OUT=${OUT:-/tmp/map_noise_memory.txt}
LEVELS=${LEVELS:-"0.25 1 3 5"}
declare -A SRC=([before]=$BEFORE [after]=$AFTER)
first=${LEVELS%% *}
for v in before after; do PYTHONPATH=${SRC[$v]} $PY -m scope3d.cli.main map $DATA$first --out /tmp/map_warm_$v --quiet >/dev/null 2>&1; done
for n in $LEVELS; do for v in before after; do
  load=$(cut -d' ' -f1-3 /proc/loadavg)
  /usr/bin/time -f "%e %U %S %M" -o /tmp/map_noise_time.txt env PYTHONPATH=${SRC[$v]} $PY -m scope3d.cli.main map $DATA$n --out /tmp/map_${v}_$n --quiet >/dev/null 2>&1
  m=$($PY -c "import json;r=json.load(open('/tmp/map_${v}_$n/report.json'));t=r['timings_s'];pe=r['pose_error'];s=r['surface_error_mm'];print(round(t['matching'],2), r['n_matches'], r['n_points'], round(pe['position_mm_mean'],4), round(s['direct']['mean'],4), round(s['after_icp']['mean'],4))")
  echo "$n $v $(cat /tmp/map_noise_time.txt) | matching_s matches points cam_mm direct icp: $m | load $load" >> $OUT
done; done
