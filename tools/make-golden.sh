#!/usr/bin/env bash
# Regenerates the golden store of the current format version. Only run this together with a
# format version bump: golden files of released versions never change (tests/golden.rs).
set -euo pipefail
cd "$(dirname "$0")/.."
version=${1:?usage: tools/make-golden.sh FORMAT_VERSION}
out=tests/data/golden-v$version
[ -e "$out" ] && { echo "$out exists; golden files of a version never change" >&2; exit 1; }
cargo run --quiet --bin octstore -- debug-synthetic "$out" --units 2 --rows 20 --seed 42 --quiet
