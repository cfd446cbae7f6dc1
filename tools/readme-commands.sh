#!/usr/bin/env bash
# Prints the shell commands of the README's "Set-up on a fresh machine" section, one per line:
# every line inside a plain ``` fence of that section. `.ci/run` runs exactly these, so the
# README's set-up commands cannot drift from what CI proves.
set -euo pipefail
readme="${1:-README.md}"
awk '
  /^## / { in_section = ($0 == "## Set-up on a fresh machine") ; next }
  in_section && /^```/ { in_fence = !in_fence; next }
  in_section && in_fence && NF > 0 { print }
' "$readme"
