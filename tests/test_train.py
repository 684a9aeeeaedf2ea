"""qtl-train: the config tree composes, the schema rejects typos, the installed CLI runs."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException

from qtl.config import register_configs
from qtl.models import DynamicsGP

TINY = [
    "+env.kwargs.horizon=8",
    "train_episodes=1",
    "test_episodes=1",
    "model.restarts=1",
    "model.max_iter=5",
]


@pytest.fixture(scope="module", autouse=True)
def _schema():
    register_configs()


def test_config_composes_with_defaults():
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        cfg = compose(config_name="train")
    assert cfg.env.id == "qtl/CartPoleSwingUp-v0"
    assert cfg.model.restarts >= 2  # several restarts by default


@pytest.mark.parametrize("override", ["trian_episodes=1", "train_episodes=abc", "model.restarts=x"])
def test_schema_rejects_typos_and_wrong_types(override):
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        with pytest.raises(ConfigCompositionException):
            compose(config_name="train", overrides=[override])


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=300)


def test_installed_cli_runs_from_any_directory_and_writes_into_its_run_dir(tmp_path):
    exe = shutil.which("qtl-train", path=str(Path(sys.executable).parent))
    assert exe is not None, "the console script qtl-train is not installed"
    run_dir = tmp_path / "run"
    done = run_cli([exe, *TINY, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (run_dir / ".hydra" / "config.yaml").is_file()
    assert list(run_dir.glob("events.out.tfevents.*")), "no TensorBoard event file"
    model = DynamicsGP.load(run_dir / "dynamics_gp.pt")
    assert model.train_x.shape == (8, 6)  # [x, ẋ, θ̇, sin θ, cos θ, u]
    assert torch.isfinite(model.hyperparameters.natural()).all()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing in the cwd


def test_python_dash_m_qtl_and_bad_override_fails(tmp_path):
    done = run_cli([sys.executable, "-m", "qtl", *TINY, f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    bad = run_cli([sys.executable, "-m", "qtl", "trian_episodes=1"], cwd=tmp_path)
    assert bad.returncode != 0 and "trian_episodes" in bad.stderr
