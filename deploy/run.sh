#!/usr/bin/env bash
# The main job: bootstraps .venv on first use, then runs the local stack
# (replay + learner + actors) with the `local` preset unless told otherwise.
# Any flag of deploy/stack.py --help may follow, e.g. --exploration.strategy softmax.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
"$root/deploy/bootstrap.sh"
cd "$root"
exec "$root/.venv/bin/python" "$root/deploy/stack.py" --preset local "$@"
