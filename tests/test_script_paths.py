"""Every path a module builds from its own place in the tree names a file or folder that is there: a module
moved to another folder (deploy/ by purpose) must carry its paths along."""

import importlib

import pytest

PATHS = [("deploy.main_job", "STACK_SCRIPT"), ("deploy.grid.grid_job", "STACK_SCRIPT"),
         ("deploy.grid.grid_job", "SOAK_SCRIPT"), ("deploy.labs.chaos", "STACK"), ("deploy.labs.netns_lab", "CONFIGS"),
         ("deploy.slurm.submit", "SCRIPT"), ("deploy.tools.readme_grid_table", "REPORT"),
         ("deploy.tools.option_reference", "PAGE")]


@pytest.mark.parametrize("module, name", PATHS)
def test_a_modules_own_paths_exist(module, name):
    path = getattr(importlib.import_module(module), name)
    assert path.exists(), f"{module}.{name} = {path}"
