#!/usr/bin/env bash
# Prints part of the README's "Python" section: `install` the lines of its plain ``` fence
# (shell commands, one per line), `example` the body of its ```python fence. `.ci/run` runs
# both, so the README's install line and example cannot drift from what CI proves.
set -euo pipefail
part="${1:?install or example}"
readme="${2:-README.md}"
awk -v part="$part" '
  /^## / { in_section = ($0 == "## Python"); next }
  in_section && /^```/ {
    if (fence == "") { fence = ($0 == "```python") ? "example" : ($0 == "```" ? "install" : "other") }
    else { fence = "" }
    next
  }
  in_section && fence == part { print }
' "$readme"
