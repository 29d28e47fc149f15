#!/bin/bash
# The 2-D A/B of issue 18 after the former plane-strain engine was removed: this checkout against
# the commit before the generic engine (19ee395, the "pre-refactor commit"), both installed side
# by side (PYTHONPATH), one thread, runs interleaved head/pre round by round. For the seed's local
# preset (chute_seed) and the nonlocal default (chute_nonlocal), END simulated seconds each (the
# default run's 596 points). Writes every run's JSON line, then per preset: the identity of the
# final states (max |difference| of x, v, σ, φ_s over their scale) and the median within-round
# ratio of the loop seconds (head / pre).
#
#   git worktree add /tmp/wt_pre 19ee395
#   bash benchmarks/ab2d-2026-12-07.sh benchmarks/results/ab2d-2026-12-07.txt [ROUNDS] [END]
#
# PRESETS="chute_nonlocal" restricts the presets; PYTHON the interpreter, PRE the other checkout.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?result file}
rounds=${2:-7}
end=${3:-1.0}
pre=${PRE:-/tmp/wt_pre}
py=${PYTHON:-python}
: > "$out.tmp"
{
  echo "# $(date -u +%FT%TZ) head $(git rev-parse --short HEAD) vs pre $(git -C "$pre" rev-parse --short HEAD); rounds=$rounds end=$end"
  echo "# load: $(cat /proc/loadavg)"
  grep -E '^cpu ' /proc/stat | awk '{print "# steal jiffies at start:", $9}'
} >> "$out.tmp"
presets=${PRESETS:-chute_seed chute_nonlocal}
for preset in $presets; do
  for tag in head pre; do  # warm-up: compile (or load) both, not timed
    src=$PWD/src; [ "$tag" = pre ] && src=$pre/src
    NUMBA_NUM_THREADS=1 PYTHONPATH=$src $py benchmarks/ab2d_identity.py "$src" "$tag" 0.01 "$preset" > /dev/null
  done
  for r in $(seq "$rounds"); do
    for tag in head pre; do
      src=$PWD/src; [ "$tag" = pre ] && src=$pre/src
      NUMBA_NUM_THREADS=1 PYTHONPATH=$src $py benchmarks/ab2d_identity.py "$src" "$tag" "$end" "$preset" >> "$out.tmp"
    done
  done
done
grep -E '^cpu ' /proc/stat | awk '{print "# steal jiffies at end:", $9}' >> "$out.tmp"
$py - "$out.tmp" >> "$out.tmp" <<'EOF'
import json, statistics, sys
import numpy as np
rows = [json.loads(l) for l in open(sys.argv[1]) if l.startswith("{")]
for preset in ("chute_seed", "chute_nonlocal"):
    if not any(r["preset"] == preset for r in rows):
        continue
    suffix = "" if preset == "chute_seed" else f"_{preset}"
    h = [r for r in rows if r["preset"] == preset and r["tag"] == "head"]
    p = [r for r in rows if r["preset"] == preset and r["tag"] == "pre"]
    ratios = [a["loop_s"] / b["loop_s"] for a, b in zip(h, p)]
    cpu = [a["cpu_s"] / b["cpu_s"] for a, b in zip(h, p) if "cpu_s" in a and "cpu_s" in b]
    a, b = np.load(f"/tmp/ab/state_head{suffix}.npz"), np.load(f"/tmp/ab/state_pre{suffix}.npz")
    diff = {k: float(np.max(np.abs(a[k] - b[k])) / max(np.max(np.abs(b[k])), 1e-300)) for k in b.files}
    print(f"# {preset}: steps head {h[0]['steps']} pre {p[0]['steps']}; n {h[0]['n']}; "
          f"loop s head {statistics.median(r['loop_s'] for r in h):.3f} pre "
          f"{statistics.median(r['loop_s'] for r in p):.3f}; median within-round ratio head/pre "
          f"{statistics.median(ratios):.3f} (range {min(ratios):.3f}-{max(ratios):.3f}); "
          + (f"CPU seconds: median ratio {statistics.median(cpu):.3f} (range {min(cpu):.3f}-"
             f"{max(cpu):.3f}), best head / best pre {min(r['cpu_s'] for r in h) / min(r['cpu_s'] for r in p):.3f}; "
             if cpu else "")
          + f"best loop s head / best pre {min(r['loop_s'] for r in h) / min(r['loop_s'] for r in p):.3f}; "
          f"max relative state difference {json.dumps(diff)}")
EOF
mv "$out.tmp" "$out"
cat "$out"
