#!/bin/bash
# The default 20 s run (the nonlocal preset), the seed's local preset and the column model of the
# default, each run once with `segmpm run` on one engine (grid.threads = "auto": one thread at
# the default run's 596 points), warm kernel cache: the loop seconds of run.json and the whole
# command's wall seconds. Run it on an idle machine (README, "Cost").
#
#   bash benchmarks/default-run-2026-12-07.sh benchmarks/results/default-run-2026-12-07.txt
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?result file}
seg=${SEGMPM:-segmpm}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
{
  echo "# $(date -u +%FT%TZ) $(git rev-parse --short HEAD); load: $(cat /proc/loadavg)"
  grep -E '^cpu ' /proc/stat | awk '{print "# steal jiffies at start:", $9}'
} > "$out.tmp"
run() {  # name, then the overrides of `segmpm run`
  local name=$1; shift
  $seg run "$@" --out "$tmp/$name" --set output.progress=false --set output.fields=false --set time.end=0.01 > /dev/null 2>&1 || true
  rm -rf "$tmp/$name"  # that short run compiled or loaded the kernels; time the 20 s one
  local t0 t1
  t0=$(date +%s.%N)
  $seg run "$@" --out "$tmp/$name" --set output.progress=false --set output.fields=false > /dev/null 2>&1
  t1=$(date +%s.%N)
  python3 - "$tmp/$name/run.json" "$name" "$t0" "$t1" >> "$out.tmp" <<'EOF'
import json, sys
r = json.load(open(sys.argv[1]))
print(json.dumps({"case": sys.argv[2], "steps": r["steps"], "n_points": r["n_points"],
                  "threads": r["threads"], "loop_s": round(r["wall_time_s"], 2),
                  "command_s": round(float(sys.argv[4]) - float(sys.argv[3]), 2),
                  "compile_or_load_s": round(r["compile_s"], 2), "status": r["status"]}))
EOF
}
run default
run local_seed chute_seed
run column_default --set 'scenario.solver="column"'
grep -E '^cpu ' /proc/stat | awk '{print "# steal jiffies at end:", $9}' >> "$out.tmp"
mv "$out.tmp" "$out"
cat "$out"
