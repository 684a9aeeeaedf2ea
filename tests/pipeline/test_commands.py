"""The pipeline's commands: an entry point each (``pyproject.toml``), runnable as ``python -m``, with one-line help."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
COMMANDS = {"qtl-experiment": "qtl.pipeline.experiment", "qtl-evaluate": "qtl.pipeline.evaluate",
            "qtl-compliance": "qtl.pipeline.compliance", "qtl-report": "qtl.report.cli"}


@pytest.mark.parametrize(("command", "module"), COMMANDS.items())
def test_each_command_is_an_entry_point_to_its_modules_main(command: str, module: str) -> None:
    scripts = (ROOT / "pyproject.toml").read_text().split("[project.scripts]")[1].split("\n[")[0]
    assert f'{command} = "{module}:main"' in scripts.splitlines()
    assert callable(importlib.import_module(module).main)


@pytest.mark.parametrize(("command", "module"), COMMANDS.items())
def test_each_command_runs_as_a_module_and_names_itself(command: str, module: str) -> None:
    done = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith(f"usage: {command} ")


def test_the_old_script_paths_are_gone() -> None:
    for name in ("run_experiment", "evaluate_policies", "compliance", "report", "benchlib"):
        assert not (ROOT / "scripts" / f"{name}.py").exists(), name
