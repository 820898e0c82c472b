#!/usr/bin/env bash
# The main job: bootstraps .venv on first use, then trains the grid's BMC cell (the `drive` preset unless
# told otherwise) with the local stack (replay + learner + actors), reads its greedy test curve, chooses its
# policy on the train starts and evaluates it (deploy/main_job.py). Any flag of deploy/launcher/stack.py --help may
# follow, e.g. --exploration.strategy softmax, or --preset local for a quick look.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
"$root/deploy/bootstrap.sh"
cd "$root"
exec "$root/.venv/bin/python" "$root/deploy/main_job.py" "$@"
