#!/usr/bin/env bash
# One cell of the grid on a lent GPU machine (issue 38, item 8): the same protocol as on the CPU
# machines (the drive preset, one actor, 30,000 updates at 4 env steps each; a cell is its updates and
# ratio, not the clock), with the learner on the GPU and the greedy test curve followed on the spare
# cores. The cell runs in its own process session, so it trains on between two calls while the machine
# is warm: call again at once with the same cell to wait on; each call packs what the cell has so far
# (its export once finished, its small files, the runner's log) into $OUT/<run>.tar.gz.
#
#   deploy/device_check.sh --wheels          here, once: the wheels the machine lacks, into .whl/
#   deploy/device_grid.sh CELL [WAIT_S]      there: start or go on with cell CELL (see --cells), wait up
#                                            to WAIT_S seconds (default 540) or until it finishes
#
# DEVICE=cpu tries it on a CPU; GRID_ARGS adds flags for every run (a short try: --updates 40 ...).
set -uo pipefail
cd "$(dirname "$0")/.."
source deploy/device_env.sh
CELL=${1:?the cell to run, a number from experiments.py --cells}
WAIT_S=${2:-540}
install_wheels || exit 1

RUNS=runs/device-grid
mkdir -p "$RUNS"
workers=$(( $(nproc) > 6 ? $(nproc) - 4 : 1 ))  # the curve's; the learner, replay, recorder and actor keep 4
# shellcheck disable=SC2206  # split on purpose: flags
grid=("$PYTHON" deploy/grid/experiments.py --buffers 1000 --seeds 0,1,2 ${GRID_ARGS:-})
run=$("${grid[@]}" --runs-dir "$RUNS" --cells | awk -v cell="$CELL" '$1 == cell {print $2}')
[ -n "$run" ] || { echo "no cell $CELL in the grid"; exit 2; }

show_machine >"$OUT/machine.txt" 2>&1

runner="experiments.py .*--cell $CELL( |$)"
if pgrep -f "$runner" >/dev/null; then
    step "cell $CELL ($run) is training: waiting on it"
else
    step "cell $CELL ($run): the learner on $DEVICE, the curve on $workers workers beside it"
    setsid nohup "${grid[@]}" --cell "$CELL" --runs-dir "$RUNS" --export "$RUNS/export" --curve-beside \
        --network.device "$DEVICE" --evaluation.workers "$workers" >>"$RUNS/$run.log" 2>&1 </dev/null &
    sleep 5
fi

deadline=$(( SECONDS + WAIT_S ))
while pgrep -f "$runner" >/dev/null && [ $SECONDS -lt $deadline ]; do
    sleep 10
    [ $(( SECONDS % 60 )) -lt 10 ] && tail -n 1 "$RUNS/$run.log" | cut -c1-220
done
pgrep -f "$runner" >/dev/null && step "still training: call again at once to go on" || step "the runner has ended"
tail -n 5 "$RUNS/$run.log"

# What comes back: the export when finished, else the run folder's small files (no policies, checkpoints,
# replay snapshot or MCAP log), and the runner's log.
tar czf "$OUT/$run.tar.gz" --exclude policies --exclude checkpoints --exclude replay --exclude '*.mcap' \
    -C "$RUNS" "$run.log" "$run" $( [ -d "$RUNS/export/$run" ] && echo "export/$run" ) 2>/dev/null
ls -la "$OUT"
