"""The transfer commands of docs/guide/transfer.md through the real CLI, and its bad-input messages, tiny budget."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard.plugins.hparams import metadata

from tests.helpers import CLI_TINY

pytestmark = pytest.mark.e2e  # runs the real CLI in subprocesses: -m 'not e2e' skips it

TINY = [*CLI_TINY, "progress=false"]


def qtl(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "qtl", *TINY, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def source_dir(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cli") / "source"
    done = qtl(f"hydra.run.dir={path}", cwd=path.parent)
    assert done.returncode == 0, done.stderr
    return path


def test_readme_transfer_command_runs_and_logs_compliance(source_dir, tmp_path):
    target = tmp_path / "target"
    done = qtl("task=cartpole", "task.env.pole_mass=2.0", f"transfer.source={source_dir}", "rule=bayesian",
               f"hydra.run.dir={target}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    with open(target / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["random", "policy"]  # rule=bayesian alone transfers θ_s, not ψ_s
    assert 0.0 <= float(rows[1]["compliance"]) <= 1.0
    assert "rule bayesian" in (target / "train.log").read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["rule=forgetting", "rule.gamma=1.2"], "rule.gamma must be in [0, 1]"),
        (["rule=sometimes"], "rule/sometimes"),
        (["approach=qtl_bayesian", "task=mountaincar", "task.horizon=6"], "transfer only works within one family"),
        (["approach=qtl_bayesian", "task.angle_dims=[]"], "angle dimensions is [2] in the source run"),
    ],
)
def test_bad_transfer_input_fails_with_the_documented_message(source_dir, tmp_path, args, message):
    run_dir = tmp_path / "run"
    done = qtl(f"transfer.source={source_dir}", *args, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert done.returncode != 0
    assert message in done.stderr
    assert not (run_dir / "metrics.csv").exists()


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> Path:
    """Two cart-pole source runs made by the CLI: ``library/m0.5`` (0.5 kg pole) and ``library/m3.0`` (3 kg)."""
    path = tmp_path_factory.mktemp("cli_library") / "library"
    for mass in ("0.5", "3.0"):
        done = qtl(f"task.env.pole_mass={mass}", f"hydra.run.dir={path / f'm{mass}'}", cwd=path.parent)
        assert done.returncode == 0, done.stderr
    return path


def test_several_sources_each_get_their_compliance_and_the_closest_is_chosen(library, tmp_path):
    target = tmp_path / "target"
    done = qtl("task.env.pole_mass=0.6", f"transfer.source=[{library / 'm0.5'},{library / 'm3.0'}]",
               "approach=qtl_bayesian", "episodes=2", f"hydra.run.dir={target}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    with open(target / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["random", "policy", "policy"]  # several sources: random initial actions
    for row in rows[1:]:  # Λ_k of both sources at every model; the 0.5 kg source (k = 0) chosen
        assert 0.0 <= float(row["compliance/1"]) < float(row["compliance/0"]) <= 1.0
        assert row["selected_source"] == "0" and row["compliance"] == row["compliance/0"]
    log = (target / "train.log").read_text()
    assert "from one of 2 sources" in log and f"{library / 'm0.5'} chosen (select=compliance)" in log
    events = EventAccumulator(str(target), size_guidance={"tensors": 0, "scalars": 0})
    events.Reload()
    assert [e.step for e in events.Scalars("transfer/compliance/1")] == [1, 2]
    assert [e.value for e in events.Scalars("transfer/selected_source")] == [0, 0]
    layout = layout_pb2.Layout.FromString(events.Tensors("custom_scalars__config__")[0].tensor_proto.string_val[0])
    assert "transfer" in [c.title for c in layout.category]
    start = metadata.parse_session_start_info_plugin_data(
        events.PluginTagToContent(metadata.PLUGIN_NAME)[metadata.SESSION_START_INFO_TAG])
    assert start.hparams["select"].string_value == "compliance" and start.hparams["sources"].number_value == 2


def test_a_directory_of_sources_and_the_mixture(library, tmp_path):
    target = tmp_path / "target"
    done = qtl("task.env.pole_mass=0.6", f"transfer.source={library}", "transfer.select=mixture", "rule=free",
               f"hydra.run.dir={target}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    with open(target / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows[1]["selected_source"] == "0" and rows[1]["compliance/1"] != ""


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["transfer.source=[{m05},{missing}]"], "is not a usable source run"),
        (["transfer.source={library}", "transfer.initial_policy={missing}"], "is not one of the sources"),
        (["transfer.source={library}", "transfer.select=vote"], "transfer.select must be one of"),
    ],
)
def test_bad_sources_fail_before_any_work(library, tmp_path, args, message):
    run_dir = tmp_path / "run"
    paths = {"m05": library / "m0.5", "missing": tmp_path / "missing", "library": library}
    done = qtl("approach=qtl_bayesian", *(a.format(**paths) for a in args), f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert done.returncode != 0
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (run_dir / "metrics.csv").exists() and not (run_dir / "checkpoints").exists()
