# Sourced by the scripts for a lent GPU machine (device_check.sh, device_grid.sh). That machine reaches no
# registry: the packages its Python lacks travel as wheels in .whl/, fetched here by `fetch_wheels`.
# Sets PYTHON, DEVICE (DEVICE=cpu tries the same steps on a CPU before a lease), OUT (the device tool's
# folder; /tmp/device-out elsewhere) and PYTHONPATH, and defines step() and show_machine().

PACKAGES="eclipse-zenoh==1.10.2 highway-env==1.12.1 gymnasium==1.4.0 farama-notifications==0.0.6
pygame-ce==2.5.8 mcap==1.6.0 zstandard==0.25.0 lz4==4.4.5"
PYTHON_VERSION=${PYTHON_VERSION:-3.12}  # the device's python3 (KINDS.md)
DEVICE=${DEVICE:-cuda}
PYTHON=${PYTHON:-python3}
OUT=${OUT:-/tmp/device-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1

step() { echo "== $(date -u +%H:%M:%S) $*"; }

show_machine() {
    step "machine"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true
    lscpu | grep -E "^Model name|^CPU\(s\)"
}

fetch_wheels() {
    local platforms="" p
    for p in manylinux_2_28 manylinux_2_27 manylinux_2_24 manylinux_2_17 manylinux2014 manylinux1; do
        platforms="$platforms --platform ${p}_x86_64"
    done
    # shellcheck disable=SC2086  # word splitting wanted: one flag, one package each
    python3 -m pip download -q --no-deps --only-binary=:all: --implementation cp \
        --python-version "$PYTHON_VERSION" $platforms -d "${WHEELS:-.whl}" $PACKAGES
}

install_wheels() {
    compgen -G "${WHEELS:-.whl}/*.whl" >/dev/null || return 0
    step "installing $(ls "${WHEELS:-.whl}" | wc -l) wheels into /tmp/device-site"
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/device-site "${WHEELS:-.whl}"/*.whl || return 1
    export PYTHONPATH=/tmp/device-site:$PWD  # the project itself is not installed there
}
