#!/bin/bash
# The default 20 s run (the nonlocal preset) against the seed's local preset, interleaved
# A/B/A/B in the same conditions, and the column model of both (warm cache, one thread each).
cd "$(dirname "$0")/.."
R=benchmarks/results/default-nonlocal-2026-12-02.txt
: > $R
date >> $R
for k in 1 2; do
  for m in local nonlocal; do
    if [ $m = local ]; then cfg="chute_seed"; else cfg=""; fi
    rm -rf /tmp/bench/d20-$m-$k
    /usr/bin/time -f "$m $k: command wall %e s" segmpm run $cfg --out /tmp/bench/d20-$m-$k --no-progress 2>> $R
    python -c "import json;d=json.load(open('/tmp/bench/d20-$m-$k/run.json'));print('$m', $k, 'steps', d['steps'], 'loop_s', round(d['wall_time_s'], 2), 'pps', round(d['particle_steps_per_second']), d['threads'], d['threads_policy'])" >> $R
  done
done
for m in local nonlocal; do
  if [ $m = local ]; then cfg="chute_seed"; else cfg=""; fi
  rm -rf /tmp/bench/col-$m
  /usr/bin/time -f "column $m: command wall %e s" segmpm run $cfg --out /tmp/bench/col-$m --set scenario.solver='"column"' --no-progress 2>> $R
  python -c "import json;d=json.load(open('/tmp/bench/col-$m/run.json'));print('column $m', 'steps', d['steps'], 'elements', d['n_points'], 'loop_s', round(d['wall_time_s'], 2))" >> $R
done
date >> $R
