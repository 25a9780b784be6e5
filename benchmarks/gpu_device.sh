#!/usr/bin/env bash
# Usage, on an offline CUDA machine from the repository root, after benchmarks/gpu_prepare.sh filled .dev/ here:
#   bash benchmarks/gpu_device.sh half [gpu_check options…]  # fast, half-res Lego, 60 s + mesh stage (~4 min, H100)
#   bash benchmarks/gpu_device.sh full [gpu_check options…]  # quality, 800² Lego, 5 min of training, scored (~7 min)
#   bash benchmarks/gpu_device.sh profile [recon bench options…]  # where a sized fast step's time goes (~1.5 min)
# Installs the carried wheels (.dev/whl) into /tmp/recon-site once (GPU_WHEELS=none: use what is installed, e.g.
# for a smoke run on a CPU with --smoke), runs benchmarks/gpu_check.py on this checkout and copies its table,
# record and the field's and mesh's reports into $OUT (default /tmp/gpu_out): a device call returns only $OUT.
# gpu_check writes its record after each part, and it is stopped after GPU_CHECK_LIMIT seconds (default 540), so a
# call cut short still returns what was measured.
set -uo pipefail
cd "$(dirname "$0")/.."
mode="${1:?half or full}"
shift
out="${OUT:-/tmp/gpu_out}"
mkdir -p "$out"
site=/tmp/recon-site
if [ "${GPU_WHEELS:-}" != none ]; then
  [ -f "$site/.installed" ] || { python3 -m pip install -q --no-index --no-deps --target "$site" .dev/whl/*.whl \
    > "$out/pip.log" 2>&1 && touch "$site/.installed"; }
  export PYTHONPATH="$site:$PWD"
fi
{ date -u; git rev-parse HEAD 2>/dev/null; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1
  python3 -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda, torch.cuda.is_available())'
  python3 -c 'import triton; print("triton", triton.__version__)' 2>&1 | tail -1; nproc; } > "$out/machine.txt"
case "$mode" in
  half) args=(--data .dev/lego_half --columns default) ;;
  full) args=(--data .dev/lego_full --preset quality --budget 5m --columns default --no-mesh --render-views 3
              --agreement-views 1) ;;
  profile) ;;
  *) echo "unknown mode '$mode': half, full or profile" >&2; exit 2 ;;
esac
work="/tmp/gpu_check_$mode"
rm -rf "$work"
if [ "$mode" = profile ]; then  # docs/profile_gpu.md's command, after the fused kernels
  timeout "${GPU_CHECK_LIMIT:-300}" python3 -m recon bench --data .dev/lego_half --presets fast --profile \
    --profile-warmup 300 --profile-steps 8 --set train.appearance=off --out "$work" "$@" > "$out/profile.log" 2>&1
  rc=$?
  cp "$work"/profile.md "$work"/profile.json "$out"/ 2>/dev/null
  tail -25 "$out/profile.log"
  exit $rc
fi
timeout "${GPU_CHECK_LIMIT:-540}" python3 benchmarks/gpu_check.py --out "$work" --quiet "${args[@]}" "$@" \
  > "$out/gpu_check_$mode.log" 2>&1
rc=$?
for name in gpu_check.json gpu_check.md; do
  [ -f "$work/$name" ] && cp "$work/$name" "$out/${name%.*}_$mode.${name##*.}"
done
for scene in "$work"/lego-*; do
  [ -d "$scene" ] || continue
  dest="$out/$(basename "$scene")"
  mkdir -p "$dest"
  cp "$scene"/03_field/metrics.json "$scene"/04_mesh/mesh_report.json "$dest"/ 2>/dev/null
  cp "$scene"/03_field/curves.png "$dest"/ 2>/dev/null
  ls "$scene"/03_field/renders/*.png 2>/dev/null | head -2 | xargs -r cp -t "$dest"/
done
tail -25 "$out/gpu_check_$mode.log"
exit $rc
