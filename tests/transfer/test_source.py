"""SourceRun: θ_s, ψ_s and data of a finished run, checked against a target before any work."""

from __future__ import annotations

import shutil

import pytest
import torch
from omegaconf import OmegaConf

from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.errors import TransferError
from qtl.features import AngleFeatures
from qtl.loop import run
from qtl.models import DynamicsGP
from qtl.task import Task
from qtl.transfer import SourceRun
from qtl.transfer.source import _stored_theta, source_dirs
from tests.helpers import tiny_config


def task_of(*overrides: str) -> Task:
    return Task.from_config(OmegaConf.to_container(tiny_config(*overrides).task, resolve=True))


def test_source_run_holds_theta_psi_and_data(finished_source):
    source = SourceRun.load(finished_source)
    state = load_checkpoint(latest_checkpoint(finished_source))
    assert source.episode == 2 and source.task.name == "cartpole"
    assert torch.equal(source.theta.lengthscales, state["theta"]["lengthscales"])
    assert source.policy.keys() == state["policy"].keys()
    assert len(source.dataset) == 3 * 8
    # Checkpoints written before θ was stored whole give the same θ from their metrics rows.
    legacy = {k: v for k, v in state.items() if k != "theta"}
    assert torch.equal(_stored_theta(legacy).natural(), source.theta.natural())


def test_missing_corrupt_or_unlearned_sources_fail_clearly(finished_source, tmp_path):
    with pytest.raises(TransferError, match="does not exist"):
        SourceRun.load(tmp_path / "nowhere")
    broken = tmp_path / "broken"
    shutil.copytree(finished_source, broken)
    latest_checkpoint(broken).write_bytes(b"not a checkpoint")
    with pytest.raises(TransferError, match="corrupt checkpoint"):
        SourceRun.load(broken)
    random_only = tmp_path / "random_only"
    run(tiny_config("episodes=0"), random_only)
    with pytest.raises(TransferError, match="no learned hyper-parameters"):
        SourceRun.load(random_only)


def test_source_of_another_family_or_dimension_is_refused_naming_both(finished_source):
    source = SourceRun.load(finished_source)
    source.check_compatible(task_of("task.env.pole_mass=2.0"))  # the same family: accepted
    with pytest.raises(TransferError, match=r"family 'qtl/CartPoleSwingUp-v0'.*family 'qtl/MountainCar-v0'"):
        source.check_compatible(task_of("task=mountaincar"))
    with pytest.raises(TransferError, match=r"angle dimensions is \[2\] in the source run .* and \[\] in the target"):
        source.check_compatible(task_of("task.angle_dims=[]"))
    assert task_of("task=quadcopter").family == task_of("task=helicopter").family == "aircraft"


class _Shaped(torch.nn.Module):
    """A module whose state dict is given: what ``check_policy`` compares."""

    def __init__(self, tensors: dict[str, torch.Tensor]) -> None:
        super().__init__()
        self.tensors = tensors

    def state_dict(self, *args, **kwargs) -> dict[str, torch.Tensor]:
        return self.tensors


def test_policy_shapes_must_match_exactly(finished_source):
    source = SourceRun.load(finished_source)
    source.check_policy(_Shaped(dict(source.policy)))
    with pytest.raises(TransferError, match="use the same policy config"):
        source.check_policy(_Shaped({k: v[..., :1] for k, v in source.policy.items()}))
    with pytest.raises(TransferError, match="the source policy"):
        source.check_policy(_Shaped({}))


def test_source_model_is_its_data_with_theta_s_unfitted(finished_source):
    source = SourceRun.load(finished_source)
    features = AngleFeatures(source.task.state_dim, source.task.angle_dims)
    model = source.model(features)
    assert isinstance(model, DynamicsGP)
    assert model.train_inputs[0].shape[-2] == len(source.dataset)
    torch.testing.assert_close(model.hyperparameters.natural(), source.theta.natural(), rtol=1e-12, atol=0)


def test_a_source_of_other_modelled_outputs_is_refused_naming_the_integration(finished_source, tmp_path):
    # The source (integration=delta) models all four outputs; a speed run on cart-pole models the velocities only.
    source = SourceRun.load(finished_source)
    assert source.outputs == (0, 1, 2, 3) and source.integration == "delta"
    message = (r"models outputs \[0, 1, 2, 3\] \(integration=delta\), this run models \[1, 3\]: "
               r"set propagation.integration=delta")
    with pytest.raises(TransferError, match=message):
        source.check_compatible(task_of(), (1, 3))
    with pytest.raises(TransferError, match=message):  # through the loop: before any work
        run(tiny_config(f"transfer.source={finished_source}", "approach=qtl_bayesian",
                        "propagation.integration=speed"), tmp_path / "target")
    assert not (tmp_path / "target").exists() or not any((tmp_path / "target").iterdir())


def test_a_speed_source_stored_with_theta_of_every_output_gives_theta_s_of_its_modelled_outputs(
        finished_source, tmp_path):
    # A run made with integration=speed before its GP held only the modelled outputs stored θ of all D.
    copy = tmp_path / "source"
    shutil.copytree(finished_source, copy)
    path = latest_checkpoint(copy)
    checkpoint = load_checkpoint(path)
    cfg = OmegaConf.create(checkpoint["config"])
    cfg.propagation.integration = "speed"
    checkpoint["config"] = OmegaConf.to_yaml(cfg)
    torch.save(checkpoint, path)
    source = SourceRun.load(copy)
    full = SourceRun.load(finished_source).theta
    assert source.outputs == (1, 3) and source.integration == "speed"
    torch.testing.assert_close(source.theta.natural(), full.natural()[[1, 3]], rtol=0, atol=0)
    model = source.model(AngleFeatures(4, source.task.angle_dims))
    assert model.outputs == (1, 3) and model.train_y.shape[-1] == 2


def test_source_dirs_reads_a_run_a_list_or_a_directory_of_runs(source_library, tmp_path):
    light, heavy = source_library / "m0.5", source_library / "m3.0"
    (source_library / "notes").mkdir(exist_ok=True)  # a subfolder without checkpoints is not a run
    assert source_dirs(str(light)) == [light.resolve()]
    assert source_dirs(str(source_library)) == [light.resolve(), heavy.resolve()]
    assert source_dirs([str(heavy), str(light)]) == [heavy.resolve(), light.resolve()]
    assert source_dirs(str(tmp_path)) == [tmp_path.resolve()]  # no run in it: SourceRun.load refuses it
