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

PACKAGES="eclipse-zenoh==1.10.2 highway-env==1.12.1 gymnasium==1.4.0 farama-notifications==0.0.6
pygame-ce==2.5.8 mcap==1.6.0 zstandard==0.25.0 lz4==4.4.5"
PYTHON_VERSION=${PYTHON_VERSION:-3.12}  # the device's python3 (KINDS.md)

if [ "${1:-}" = "--wheels" ]; then
    platforms=""
    for p in manylinux_2_28 manylinux_2_27 manylinux_2_24 manylinux_2_17 manylinux2014 manylinux1; do
        platforms="$platforms --platform ${p}_x86_64"
    done
    exec python3 -m pip download -q --no-deps --only-binary=:all: --implementation cp \
        --python-version "$PYTHON_VERSION" $platforms -d "${WHEELS:-.whl}" $PACKAGES
fi

STACK_S=${1:-300}
DEVICE=${DEVICE:-cuda}
PYTHON=${PYTHON:-python3}
OUT=${OUT:-/tmp/device-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
step() { echo "== $(date -u +%H:%M:%S) $*"; }

if compgen -G "${WHEELS:-.whl}/*.whl" >/dev/null; then
    step "installing $(ls "${WHEELS:-.whl}" | wc -l) wheels into /tmp/device-site"
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/device-site "${WHEELS:-.whl}"/*.whl || exit 1
    export PYTHONPATH=/tmp/device-site:$PWD  # the project itself is not installed there
fi

{
    step "machine"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true
    lscpu | grep -E "^Model name|^CPU\(s\)"
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
timeout -s TERM -k 60 "$STACK_S" "$PYTHON" deploy/stack.py --preset paper --actors "$actors" \
    --network.device "$DEVICE" --run.runs_dir /tmp/device-runs --run.name device-paper \
    2>&1 | tee "$OUT/stack.txt"
sleep 5  # the stack's own shutdown writes the last status
run=/tmp/device-runs/device-paper
cp "$run/status.json" "$run/summary.json" "$OUT/" 2>/dev/null
tail -n 40 "$run/logs/learner.log" >"$OUT/learner-log-tail.txt" 2>/dev/null
step "done"
