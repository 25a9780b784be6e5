#!/usr/bin/env bash
# The realistic generated tabletop (14 photos, 1600x1200, clutter, gloss, auto exposure, blur, lens distortion) run as
# a user runs it: photos alone, no masks, `fast` preset. Scores the poses against the true cameras, the automatic
# masks and the mesh's silhouette against the true masks, and the mesh against the object's true surface.
# Writes benchmarks/results/tabletop_realistic_fast.{json,md}.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${BENCH_WORK:-$(mktemp -d)}"
recon bench --data tabletop_realistic --presets fast --out "$work" "$@"
cp "$work/bench.json" benchmarks/results/tabletop_realistic_fast.json
grep -v '^!\[' "$work/bench.md" > benchmarks/results/tabletop_realistic_fast.md
echo "record: benchmarks/results/tabletop_realistic_fast.json (scenes in $work)"
