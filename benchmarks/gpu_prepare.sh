#!/usr/bin/env bash
# Usage: benchmarks/gpu_prepare.sh        (on a machine with network, from anywhere in the checkout)
# Fills .dev/ (git-ignored) with what an offline CUDA machine needs for benchmarks/gpu_device.sh:
#   .dev/whl/         wheels of the packages such a machine may lack (trimesh, fast-simplification, xatlas; the
#                     versions constraints.txt pins), for $GPU_PYTHON (default 3.12) on manylinux x86_64
#   .dev/lego_half/   the half-resolution Lego's train and test splits (its val split is never used)
#   .dev/lego_full/   benchmarks/lego_full_res.py's folder: the 800² training photos, half-res test views
# A device call carries at most 64 MiB: one of the two Lego folders a call, with the wheels (the sizes are printed).
set -euo pipefail
cd "$(dirname "$0")/.."
py="${GPU_PYTHON:-3.12}"
shared="$(cd .. && pwd)/shared/data"
mkdir -p .dev/whl
for pkg in trimesh fast-simplification xatlas; do
  pin=$(grep -i "^$pkg==" constraints.txt || true)
  pip download -q --no-deps --only-binary=:all: --python-version "$py" --platform manylinux_2_28_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .dev/whl "${pin:-$pkg}"
done
if [ ! -f .dev/lego_half/transforms_test.json ]; then
  mkdir -p .dev/lego_half
  cp -r "$shared/nerf_synthetic_lego_half/train" "$shared/nerf_synthetic_lego_half/test" \
    "$shared/nerf_synthetic_lego_half/transforms_train.json" "$shared/nerf_synthetic_lego_half/transforms_test.json" \
    .dev/lego_half/
fi
# rebuilt when an older copy holds another number of test views than lego_full_res.py's default (50, to fit a call)
if [ "$(ls .dev/lego_full/test 2>/dev/null | wc -l)" != 50 ]; then
  rm -rf .dev/lego_full
  python benchmarks/lego_full_res.py --out .dev/lego_full
fi
du -sh .dev/whl .dev/lego_half .dev/lego_full
echo 'carry [".dev/whl", ".dev/lego_half"] for `bash benchmarks/gpu_device.sh half`, [".dev/whl", ".dev/lego_full"] for `full`'
