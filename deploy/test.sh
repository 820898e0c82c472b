#!/usr/bin/env bash
# The test command: bootstraps .venv on first use, then runs the whole suite.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
"$root/deploy/bootstrap.sh"
cd "$root"
exec "$root/.venv/bin/python" -m pytest "$@"
