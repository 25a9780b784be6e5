#!/usr/bin/env bash
# The fox (../shared/data/fox/images, 67 phone-video frames of a mounted fox head on a papered wall) run as a user runs
# it: photos alone (structure from motion, automatic masks), `fast` preset. Scores the held-out photos (test PSNR, each
# photo's appearance fitted on its left half); the fox has no true surface, so no mesh accuracy.
# Writes benchmarks/results/fox_fast.{json,md}.
exec "$(dirname "$0")/record.sh" fox fast "$@"
