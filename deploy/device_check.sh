#!/usr/bin/env bash
# The one prepared run for a lent GPU machine (docs/deployment.md, On a GPU): the CUDA tests,
# the learner's speed on the GPU, then the paper's method as a stack with the
# learner on the GPU and the actors on the CPU cores, until the time is up.
# Everything it reports goes to $OUT (the device tool's folder; /tmp/device-out
# elsewhere). The machine reaches no registry: the packages its Python lacks
# travel as wheels in .whl/ (made by `deploy/device_check.sh --wheels`).
#
#   deploy/device_check.sh --wheels        here: fetch the wheels into .whl/
#   deploy/device_check.sh [STACK_SECONDS]  there: the checks (default 300 s)
#
# DEVICE=cpu runs the same steps on a CPU, to test the set-up before a lease.
set -uo pipefail
cd "$(dirname "$0")/.."

source deploy/device_env.sh
if [ "${1:-}" = "--wheels" ]; then
    fetch_wheels
    exit
fi
STACK_S=${1:-300}
install_wheels || exit 1

{
    show_machine
    "$PYTHON" -c "import torch, zenoh, highway_env, mcap; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
} 2>&1 | tee "$OUT/machine.txt"

step "the CUDA tests"
"$PYTHON" -m pytest -q -p no:cacheprovider -rs tests/test_network.py tests/test_update.py tests/test_config.py \
    -k "cuda" 2>&1 | tee "$OUT/cuda-tests.txt"

step "learner speed on $DEVICE"
timeout 240 "$PYTHON" deploy/bench/learner_speed.py --network.device "$DEVICE" --rounds 3 \
    ${SPEED_ARGS:-} 2>&1 | tee "$OUT/learner-speed.txt"

actors=$(( $(nproc) > 6 ? $(nproc) - 4 : 1 ))
step "the paper's method for ${STACK_S} s: learner on $DEVICE, $actors actors on the CPU"
rm -rf /tmp/device-runs
timeout -s TERM -k 60 "$STACK_S" "$PYTHON" deploy/launcher/stack.py --preset paper --actors "$actors" \
    --network.device "$DEVICE" --run.runs_dir /tmp/device-runs --run.name device-paper \
    2>&1 | tee "$OUT/stack.txt"
sleep 5  # the stack's own shutdown writes the last status
run=/tmp/device-runs/device-paper
cp "$run/status.json" "$run/summary.json" "$OUT/" 2>/dev/null
tail -n 40 "$run/logs/learner.log" >"$OUT/learner-log-tail.txt" 2>/dev/null
step "done"
