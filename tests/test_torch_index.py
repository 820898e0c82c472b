"""deploy/torch_index.py: where bootstrap installs torch from, read from pip's configuration (offline)."""

import os
import subprocess
import sys
from pathlib import Path

from deploy.torch_index import CPU_INDEX, torch_index_options

SCRIPT = Path(__file__).resolve().parents[1] / "deploy" / "torch_index.py"


def options_under(**pip_environment: str) -> list[str]:
    """The script's answer with no pip.conf and none of this machine's PIP_* variables, plus these."""
    env = {name: value for name, value in os.environ.items() if not name.startswith("PIP_")}
    env.update({"PIP_CONFIG_FILE": os.devnull, **pip_environment})
    result = subprocess.run([sys.executable, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60,
                            check=True)
    return result.stdout.split()


def test_a_stock_machine_gets_the_cpu_index():
    assert options_under() == ["--index-url", CPU_INDEX]


def test_local_wheels_in_pip_configuration_are_used_instead(tmp_path):
    assert options_under(PIP_FIND_LINKS=str(tmp_path)) == []
    config = tmp_path / "pip.conf"
    config.write_text(f"[install]\nfind-links = {tmp_path}\n")
    assert options_under(PIP_CONFIG_FILE=str(config)) == []


def test_an_index_of_its_own_is_no_local_wheel():
    listing = "global.index-url='https://mirror.example/simple'\n:env:.default-timeout='180'\n"
    assert torch_index_options(listing) == ["--index-url", CPU_INDEX]
