#!/usr/bin/env bash
# Comparison benchmarks against Open3D (TSDF VoxelBlockGrid, screened Poisson). Not part of CI.
# Sets up its own Python environment (tools/bench/.venv, pinned by requirements.txt), builds
# octstore in release mode, runs tools/bench/bench.py and writes BENCHMARKS.md and benchmarks/.
#
#   tools/bench/run.sh                                # everything
#   tools/bench/run.sh --quick --sections groundtruth # the bunny at one noise level
set -euo pipefail
cd "$(dirname "$0")/../.."
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  # Open3D's wheel links libusb; on Debian it is the package libusb-1.0-0.
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "Open3D needs libusb-1.0: sudo apt-get install libusb-1.0-0" >&2
    exit 1
  fi
fi
venv=tools/bench/.venv
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
fi
"$venv/bin/pip" install --quiet --disable-pip-version-check -r tools/bench/requirements.txt
cargo build --release --quiet
exec "$venv/bin/python" tools/bench/bench.py "$@"
