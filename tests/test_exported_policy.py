"""A run's policy exported: the library's actions to round-off, as TorchScript and torch.export, loaded without qtl."""

from __future__ import annotations

import subprocess
import sys
import warnings

import pytest
import torch

from qtl.build import build
from qtl.errors import UserError
from qtl.exported_policy import check_export_path, exported_policy, save_policy
from qtl.policies import SquashedPolicy
from tests.helpers import tiny_config

TOL = {"rtol": 1e-12, "atol": 1e-12}


@pytest.fixture(scope="module", params=["rbf", "rbf_network", "linear"])
def parts_and_policy(request):
    """A tiny cart-pole's parts (θ an angle) and a squashed policy of the kind, ψ moved off its initial values."""
    parts = build(tiny_config(f"policy={request.param}"))
    policy = parts.initial_policy()
    gen = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    return parts, policy


def states(count: int = 500) -> torch.Tensor:
    """Random raw cart-pole states `count x 4`, angles well beyond ±π."""
    gen = torch.Generator().manual_seed(0)
    return torch.randn(count, 4, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 2.0, 6.0, 5.0],
                                                                                    dtype=torch.float64)


def library_actions(parts, policy: SquashedPolicy, x: torch.Tensor) -> torch.Tensor:
    """What the run's actor does, point by point (the real system's path) and batched."""
    with torch.no_grad():
        return torch.stack([torch.as_tensor(parts.actor(policy)(row.numpy())) for row in x])


def test_the_exported_policy_acts_as_the_library_does(parts_and_policy, tmp_path):
    parts, policy = parts_and_policy
    x = states()
    want = library_actions(parts, policy, x)
    module = exported_policy(policy, parts.features)
    torch.testing.assert_close(module(x), want, **TOL)
    torch.testing.assert_close(module(x[0]), want[0], **TOL)  # one state `D`
    with torch.no_grad():
        torch.testing.assert_close(module(x), policy(parts.features(x)), **TOL)
    assert module(x.float()).dtype == torch.float64  # the input is cast to the policy's dtype
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch 2.13 calls TorchScript deprecated
        scripted = torch.jit.load(str(save_policy(tmp_path / "p.pt", module)))
    torch.testing.assert_close(scripted(x), want, **TOL)
    program = torch.export.load(str(save_policy(tmp_path / "deep" / "p.pt2", module))).module()
    torch.testing.assert_close(program(x), want, **TOL)


def test_the_centre_of_asymmetric_bounds_is_added(parts_and_policy):
    parts, policy = parts_and_policy
    x = states(20)
    shifted = exported_policy(policy, parts.features, centre=[0.25])
    torch.testing.assert_close(shifted(x), library_actions(parts, policy, x) + 0.25, **TOL)


def test_what_cannot_be_exported_is_one_line(parts_and_policy, tmp_path):
    parts, policy = parts_and_policy
    with pytest.raises(UserError, match=r"must end in \.pt \(TorchScript, torch\.jit\.load\) or \.pt2"):
        check_export_path(tmp_path / "policy.onnx")
    with pytest.raises(UserError, match="squashed policy is expected"):
        exported_policy(policy.policy, parts.features)


@pytest.mark.e2e  # a fresh interpreter
def test_the_torchscript_file_runs_in_a_process_that_never_imports_qtl(tmp_path):
    parts = build(tiny_config())
    policy = parts.initial_policy()
    x = states(10)
    path = save_policy(tmp_path / "policy.pt", exported_policy(policy, parts.features))
    torch.save(x, tmp_path / "x.pt")
    probe = ("import sys, warnings, torch; warnings.simplefilter('ignore'); "
             f"m = torch.jit.load({str(path)!r}); x = torch.load({str(tmp_path / 'x.pt')!r}); "
             f"torch.save(m(x), {str(tmp_path / 'u.pt')!r}); "
             "print(sorted(n for n in sys.modules if n.split('.')[0] == 'qtl'))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
    torch.testing.assert_close(torch.load(tmp_path / "u.pt"), library_actions(parts, policy, x), **TOL)
