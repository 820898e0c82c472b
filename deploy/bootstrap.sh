#!/usr/bin/env bash
# Creates the project's virtual environment on first use and reinstalls only
# when pyproject.toml or this script changes, so later runs start at once.
#
# CPU machines get torch==2.13.0, a CPU build: from PyTorch's CPU index, not PyPI's
# CUDA build, unless pip's configuration names local wheels (deploy/torch_index.py).
# A GPU user installs their own torch into .venv first (see README); a torch
# already present is left alone.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv="$root/.venv"
stamp="$venv/.d3rqn-installed"
want=$(cat "$root/pyproject.toml" "$root/deploy/bootstrap.sh" | sha256sum | cut -d' ' -f1)

if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
    exit 0
fi

python=${PYTHON:-}
if [ -z "$python" ]; then
    for candidate in python3.11 python3 python; do
        if command -v "$candidate" >/dev/null 2>&1; then python=$candidate; break; fi
    done
fi
echo "[bootstrap] setting up $venv with $($python --version 2>&1)" >&2
[ -x "$venv/bin/python" ] || "$python" -m venv "$venv"
pip=("$venv/bin/python" -m pip --disable-pip-version-check -q)
if ! "$venv/bin/python" -c "import torch" >/dev/null 2>&1; then
    torch_index=$("$venv/bin/python" "$root/deploy/torch_index.py")  # "--index-url URL", or empty
    echo "[bootstrap] installing torch==${D3RQN_TORCH_VERSION:-2.13.0} (CPU build${torch_index:+ from ${torch_index#--index-url }})" >&2
    # shellcheck disable=SC2086  # unquoted on purpose: no word or two
    "${pip[@]}" install $torch_index "torch==${D3RQN_TORCH_VERSION:-2.13.0}"
fi
echo "[bootstrap] installing d3rqn and its dependencies" >&2
"${pip[@]}" install -e "$root[test]"
echo "$want" > "$stamp"
echo "[bootstrap] done" >&2
