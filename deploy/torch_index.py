"""Where deploy/bootstrap.sh installs torch from, decided by pip's own configuration.

PyPI's torch for Linux is the multi-GB CUDA build, so a stock machine gets torch from
PyTorch's CPU index. A machine whose pip configuration (a pip.conf file or a PIP_*
variable) names local wheels with find-links installs torch from those, as it does every
other package: it may have no way out to the internet.

    python deploy/torch_index.py    # prints the pip options for torch, or nothing
"""

from __future__ import annotations

import subprocess
import sys

CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def torch_index_options(pip_config_listing: str) -> list[str]:
    """The pip options for installing torch, given the output of `pip config list`."""
    # Lines look like "global.find-links='/opt/wheels'" or ":env:.find-links='/opt/wheels'".
    names = {line.split("=", 1)[0].rsplit(".", 1)[-1] for line in pip_config_listing.splitlines()}
    return [] if "find-links" in names else ["--index-url", CPU_INDEX]


def pip_config_listing() -> str:
    return subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True,
                          check=True).stdout


if __name__ == "__main__":
    print(" ".join(torch_index_options(pip_config_listing())))
