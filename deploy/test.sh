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
# The network-namespace labs run after them, alone: beside another file their processes were starved into
# faults of their own. Exit 5 of a part is "no test selected there" (a selection of files, say).
pytest=("$root/.venv/bin/python" -m pytest)
rest=0 labs=0
"${pytest[@]}" -n "${D3RQN_TEST_WORKERS:-2}" --dist loadfile -m "not lab" "$@" || rest=$?
"${pytest[@]}" -m lab "$@" || labs=$?
[ "$rest" = 5 ] && [ "$labs" = 5 ] && exit 5
for status in "$rest" "$labs"; do
    [ "$status" = 0 ] || [ "$status" = 5 ] || exit "$status"
done
exit 0
