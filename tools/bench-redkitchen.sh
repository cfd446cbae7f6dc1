#!/usr/bin/env bash
# Ingest + octree build (and optionally the whole solve) on subsets of the RedKitchen frames,
# printing input size, cubes, wall time and peak RSS per step. Not part of CI.
#
#   tools/bench-redkitchen.sh [FRAMES...] (default: 100 300 1000)
#   UNTIL=solution MEMORY=512MiB ITERATIONS=50 tools/bench-redkitchen.sh 100
set -euo pipefail
cd "$(dirname "$0")/.."
data=../shared/data/7scenes-redkitchen
until=${UNTIL:-octree}
memory=${MEMORY:-512MiB}
iterations=${ITERATIONS:-200}
cargo build --release --quiet
bin=target/release/octstore
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
printf '%-7s %-10s %-12s %-12s %-10s %-10s %-10s %s\n' frames stage samples cubes seconds peak_MB units detail
for frames in "${@:-100 300 1000}"; do
  stride=$((1000 / frames))
  store=$work/s$frames
  out=$($bin --memory-budget "$memory" --quiet ingest "$store" "$data" --stride "$stride" --limit "$frames")
  samples=$(sed -n 's/.*: \([0-9]*\) samples.*/\1/p' <<<"$out")
  secs=$(sed -n 's/.*| \([0-9.]*\)s | peak memory \([0-9]*\) MB.*/\1/p' <<<"$out")
  peak=$(sed -n 's/.*peak memory \([0-9]*\) MB.*/\1/p' <<<"$out")
  printf '%-7s %-10s %-12s %-12s %-10s %-10s\n' "$frames" ingest "$samples" - "$secs" "$peak"
  $bin --memory-budget "$memory" --quiet solve "$store" --until "$until" --iterations "$iterations" | while IFS= read -r line; do
    stage=$(awk '{print $1}' <<<"$line")
    rows=$(sed -n 's/.*| rows \([0-9]*\) |.*/\1/p' <<<"$line")
    secs=$(sed -n 's/.*| \([0-9.]*\)s | peak.*/\1/p' <<<"$line")
    peak=$(sed -n 's/.*peak memory \([0-9]*\) MB.*/\1/p' <<<"$line")
    units=$(sed -n 's/.*| units \([0-9]*\) .*/\1/p' <<<"$line")
    detail=$(sed -n 's/.*: \([0-9]*\) votes.*/\1 votes/p' <<<"$line")
    printf '%-7s %-10s %-12s %-12s %-10s %-10s %-10s %s\n' "$frames" "$stage" "$samples" "$rows" "$secs" "$peak" "$units" "$detail"
  done
done
