#!/usr/bin/env bash
# The shipped sample with the `fast` preset, as the README's first command trains it (4-minute budget), then the
# mesh scored against the sample's true surface. Writes benchmarks/results/sample_fast.{json,md}.
exec "$(dirname "$0")/record.sh" sample fast "$@"
