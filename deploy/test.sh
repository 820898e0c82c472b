#!/usr/bin/env bash
# The test command: bootstraps .venv on first use, then runs the whole suite.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
"$root/deploy/bootstrap.sh"
# The network-fault tests drop packets with nftables; as root on Debian, install it once (else they skip).
if [ "$(id -u)" = 0 ] && ! command -v nft >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
    echo "[test] installing nftables for the network-fault tests" >&2
    apt-get install -y -q nftables >/dev/null 2>&1 || echo "[test] could not install nftables: those tests skip" >&2
fi
cd "$root"
# Two workers, a test file each at a time (its module fixtures run once); most tests wait on processes, so
# two files beside each other fit 2 cores. D3RQN_TEST_WORKERS=0 runs in this process, as does `-n 0` given last.
exec "$root/.venv/bin/python" -m pytest -n "${D3RQN_TEST_WORKERS:-2}" --dist loadfile "$@"
