#!/usr/bin/env bash
# The shipped sample with the `fast` preset, as the README's first command trains it (4-minute budget), then the
# mesh scored against the sample's true surface. Writes benchmarks/results/sample_fast.{json,md}.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${BENCH_WORK:-$(mktemp -d)}"
recon bench --data sample --presets fast --out "$work" "$@"
cp "$work/bench.json" benchmarks/results/sample_fast.json
# the table without its plots (they stay in $work)
grep -v '^!\[' "$work/bench.md" > benchmarks/results/sample_fast.md
echo "record: benchmarks/results/sample_fast.json (scenes in $work)"
