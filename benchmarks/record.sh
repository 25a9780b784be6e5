#!/usr/bin/env bash
# Usage: benchmarks/record.sh DATA PRESETS [recon bench options…]
# Runs `recon bench --data DATA --presets PRESETS` in a scratch folder ($BENCH_WORK or a new temporary one) and
# copies its record into benchmarks/results/<DATA>_<PRESETS>.{json,md} (the table without its plots), or
# <$RECORD_NAME>.{json,md} when that is set (a run with other options than the preset's).
set -euo pipefail
cd "$(dirname "$0")/.."
data="$1" presets="$2"
shift 2
name="${RECORD_NAME:-${data}_${presets//,/_}}"
work="${BENCH_WORK:-$(mktemp -d)}"
recon bench --data "$data" --presets "$presets" --out "$work" "$@"
cp "$work/bench.json" "benchmarks/results/$name.json"
grep -v '^!\[' "$work/bench.md" > "benchmarks/results/$name.md"
echo "record: benchmarks/results/$name.json (scenes in $work)"
