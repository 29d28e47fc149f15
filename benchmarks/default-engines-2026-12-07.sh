#!/bin/bash
# The default 20 s run (the nonlocal preset) and the seed's local preset on the default engine
# (the dimension-generic one since 2026-12-07) and on the former production engine, interleaved
# in the same conditions, then the column model of both presets on the default engine (warm
# cache, one thread each: grid.threads = "auto" for 596 points). Writes
# benchmarks/results/default-engines-2026-12-07.txt.
cd "$(dirname "$0")/.."
R=${1:-benchmarks/results/default-engines-2026-12-07.txt}  # the result file (argument 1)
: > $R
date >> $R
awk '/^cpu /{print "steal jiffies (cumulative):", $9}' /proc/stat >> $R
for m in nonlocal local; do
  for e in auto production; do
    if [ $m = local ]; then cfg="chute_seed"; else cfg=""; fi
    o=/tmp/bench/d20-$m-$e
    rm -rf $o
    /usr/bin/time -f "$m $e: command wall %e s" segmpm run $cfg --out $o --no-progress \
      --set grid.engine="'$e'" 2>> $R
    python -c "import json;d=json.load(open('$o/run.json'));print('$m', '$e', 'steps', d['steps'], 'loop_s', round(d['wall_time_s'], 2), 'pps', round(d['particle_steps_per_second']), d['threads'], d['threads_policy'])" >> $R
  done
done
for m in nonlocal local; do
  if [ $m = local ]; then cfg="chute_seed"; else cfg=""; fi
  o=/tmp/bench/col-$m
  rm -rf $o
  /usr/bin/time -f "column $m: command wall %e s" segmpm run $cfg --out $o --set scenario.solver='"column"' --no-progress 2>> $R
  python -c "import json;d=json.load(open('$o/run.json'));print('column $m', 'steps', d['steps'], 'elements', d['n_points'], 'loop_s', round(d['wall_time_s'], 2))" >> $R
done
date >> $R
