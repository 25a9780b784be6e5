#!/usr/bin/env bash
# The fox as issue 34 first measured it: its 67 photos (structure from motion), `fast`, automatic masks off, so the
# capture trains as an unbounded scene on whole photos (the papered wall, the mirror) and the held-out photos are
# scored whole (each photo's appearance fitted on its left half). Writes benchmarks/results/fox_fast_masks_off.{json,md}.
RECORD_NAME=fox_fast_masks_off exec "$(dirname "$0")/record.sh" fox fast --set normalize.masks=off "$@"
