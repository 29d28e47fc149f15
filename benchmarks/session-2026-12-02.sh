#!/bin/bash
# idle-machine measurements of this session, in one go
cd "$(dirname "$0")/.."
R=benchmarks/results
D=2026-12-02
set -x
date
# 1. the threads crossover and the nonlocal cost ratio (interleaved variants, no peer)
segmpm bench --sizes 600 2000 5000 10000 20000 32000 --threads 1 2 --steps 400 --repeats 3 --no-peer --variants local nonlocal --json $R/bench-$D-crossover.json > $R/bench-$D-crossover.txt 2>&1
date
# 2. the seed case: local default vs the nonlocal preset, 2 s simulated, interleaved A/B/A/B
for k in 1 2; do
  for m in local nonlocal; do
    if [ $m = local ]; then cfg=""; else cfg="examples/chute_nonlocal.toml"; fi
    rm -rf /tmp/bench/seed-$m-$k
    /usr/bin/time -f "$m $k wall %e s" segmpm run $cfg --out /tmp/bench/seed-$m-$k --set time.end=2.0 --set output.fields=false --set output.figures=false --no-progress 2>> $R/seed-ab-$D.txt
    python -c "import json;d=json.load(open('/tmp/bench/seed-$m-$k/run.json'));print('$m', $k, d['steps'], d['wall_time_s'], d['particle_steps_per_second'], d['threads'], d['threads_policy'])" >> $R/seed-ab-$D.txt
  done
done
# 2b. the default 20 s seed case, as a user runs it (warm cache)
rm -rf /tmp/bench/seed20
/usr/bin/time -f "default 20 s: command wall %e s" segmpm run --out /tmp/bench/seed20 --no-progress 2>> $R/seed-ab-$D.txt
python -c "import json;d=json.load(open('/tmp/bench/seed20/run.json'));print('default20', d['steps'], d['wall_time_s'], d['particle_steps_per_second'], d['threads'], d['threads_policy'], d['threading_layer'])" >> $R/seed-ab-$D.txt
date
# 3. the peer table with both initial orders
segmpm bench --sizes 8000 32000 --threads 1 2 --steps 400 --repeats 5 --json $R/bench-$D-peer.json > $R/bench-$D-peer.txt 2>&1
date
# 4. contention
segmpm bench --contended --sizes 596 32000 --threads 1 2 --steps 400 --repeats 3 --json $R/bench-$D-contended.json > $R/bench-$D-contended.txt 2>&1
date
