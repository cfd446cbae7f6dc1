#!/usr/bin/env bash
# SSD's solve against TGV's on the same voted RedKitchen store, side by side: ingests the frames
# once (`--sample-sums`), votes once (`solve --until histograms`), then alternates `solve
# --method tgv` and `solve --method ssd` on fresh copies of that store, so that both meet the
# same minutes of a machine whose speed drifts. Prints each run's wall and user time, peak RSS,
# SSD's samples stage and the round's ratio. Not part of CI (docs/parameters.md, "Solvers").
#
#   tools/ssd-vs-tgv.sh                       (1000 frames, 3 rounds)
#   FRAMES=100 ROUNDS=2 MEMORY=512MiB tools/ssd-vs-tgv.sh
set -euo pipefail
cd "$(dirname "$0")/.."
data=../shared/data/7scenes-redkitchen
frames=${FRAMES:-1000}
rounds=${ROUNDS:-3}
memory=${MEMORY:-512MiB}
[ -x /usr/bin/time ] || { echo "tools/ssd-vs-tgv.sh needs GNU time (/usr/bin/time; Debian: apt-get install time)" >&2; exit 1; }
[ -d "$data" ] || { echo "tools/ssd-vs-tgv.sh: no RedKitchen frames at $data" >&2; exit 1; }
cargo build --release --quiet
bin=$PWD/target/release/octstore
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
stride=$((1000 / frames))
"$bin" --memory-budget "$memory" --quiet ingest "$work/voted" "$data" --stride "$stride" --limit "$frames" --max-depth 10 --sample-sums >/dev/null
"$bin" --memory-budget "$memory" --quiet solve "$work/voted" --until histograms >/dev/null
# One solve of a copy: sets wall, user, peak (MiB) and samples (SSD's samples stage, or -).
solve() {
  rm -rf "$work/copy"
  cp -r "$work/voted" "$work/copy"
  if ! /usr/bin/time -f '%e %U %M' -o "$work/time" "$bin" --memory-budget "$memory" solve "$work/copy" --method "$1" --quiet >"$work/log"; then
    echo "tools/ssd-vs-tgv.sh: solve --method $1 failed (its error is above)" >&2
    exit 1
  fi
  local peak_kib
  read -r wall user peak_kib <"$work/time"
  peak=$((peak_kib / 1024))
  samples=$(sed -n 's/^samples .*| \([0-9.]*\)s | peak.*/\1/p' "$work/log")
  samples=${samples:--}
}
printf '%-6s %-6s %-9s %-9s %-9s %-9s %s\n' round method wall_s user_s peak_MiB samples_s ssd/tgv
for round in $(seq 1 "$rounds"); do
  solve tgv
  tgv_wall=$wall
  printf '%-6s %-6s %-9s %-9s %-9s %-9s\n' "$round" tgv "$wall" "$user" "$peak" -
  solve ssd
  ratio=$(awk -v s="$wall" -v t="$tgv_wall" 'BEGIN { printf "%.2f", s / t }')
  printf '%-6s %-6s %-9s %-9s %-9s %-9s %s\n' "$round" ssd "$wall" "$user" "$peak" "$samples" "$ratio"
done
