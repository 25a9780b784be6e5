#!/usr/bin/env bash
# The realistic generated tabletop (14 photos, 1600x1200, clutter, gloss, auto exposure, blur, lens distortion) run as
# a user runs it: photos alone, no masks, `fast` preset. Scores the poses against the true cameras, the automatic
# masks and the mesh's silhouette against the true masks, and the mesh against the object's true surface.
# Writes benchmarks/results/tabletop_realistic_fast.{json,md}.
exec "$(dirname "$0")/record.sh" tabletop_realistic fast "$@"
