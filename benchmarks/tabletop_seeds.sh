#!/usr/bin/env bash
# Usage: benchmarks/tabletop_seeds.sh [recon bench options…]   (SEEDS="1 2 3" by default)
# The realistic generated tabletop drawn again from other seeds (another camera path, textures, exposures, noise),
# `fast`, from its photos alone: whether the no-mask path (SfM, automatic masks, field, mesh) holds beyond the one
# draw benchmarks/results/tabletop_realistic_fast.json records. Each seed is one `recon bench --data
# tabletop_realistic@SEED --presets fast`; their rows are written together to
# benchmarks/results/tabletop_realistic_seeds.{json,md}.
set -euo pipefail
cd "$(dirname "$0")/.."
read -r -a seeds <<< "${SEEDS:-1 2 3}"
work="${BENCH_WORK:-$(mktemp -d)}"
for seed in "${seeds[@]}"; do
  recon bench --data "tabletop_realistic@$seed" --presets fast --out "$work/seed$seed" "$@"
done
python - "$work" "${seeds[@]}" <<'PY'
import json, sys
from pathlib import Path

work, seeds = Path(sys.argv[1]), sys.argv[2:]
rows = [row for seed in seeds for row in json.loads((work / f"seed{seed}" / "bench.json").read_text())]
Path("benchmarks/results/tabletop_realistic_seeds.json").write_text(json.dumps(rows, indent=1) + "\n")
tables = [(work / f"seed{seed}" / "bench.md").read_text() for seed in seeds]
text = "\n".join(line for table in tables for line in table.splitlines() if not line.startswith("!["))
Path("benchmarks/results/tabletop_realistic_seeds.md").write_text(text + "\n")
PY
echo "record: benchmarks/results/tabletop_realistic_seeds.json (scenes in $work)"
