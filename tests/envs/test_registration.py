"""Every id of `qtl.envs.ENV_IDS` is registered and honours the project's env contract.

The contract (what the learner relies on), for every env:
- `gymnasium.make(id)` works without a TimeLimit wrapper; `check_env(env.unwrapped)` passes;
- `reset(seed=...)` is deterministic; `terminated` is False, `truncated` True exactly at step
  `horizon`;
- `info["state"]` is the noise-free state, shaped like the observation, and the reward of a step
  is `reward_spec(info["state"])` for a `SaturatingReward` `reward_spec`;
- `start_mean` / `start_std` give the start distribution per observation dimension;
- `render_mode="rgb_array"` returns an `H x W x 3` `uint8` frame;
- the class docstring has Gymnasium's classic-control sections and documents the
  `reset(options={"state": ...})` option.
"""

from __future__ import annotations

import importlib
import inspect
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from qtl import envs
from qtl.envs.rewards import SaturatingReward

ALL_IDS = sorted(envs.ENV_IDS)
N_DETERMINISM_STEPS = 5
DOC_SECTIONS = (
    "Description",
    "Action Space",
    "Observation Space",
    "Rewards",
    "Starting State",
    "Episode Truncation",
    "Arguments",
)
PUBLIC_NAMES = {
    "CartPoleSwingUpEnv": "qtl.envs.cartpole",
    "MountainCarEnv": "qtl.envs.mountain_car",
    "QuadcopterEnv": "qtl.envs.aircraft",
    "HelicopterEnv": "qtl.envs.aircraft",
    "Autopilot": "qtl.envs.aircraft",
    "ground_effect_factor": "qtl.envs.aircraft",
    "SaturatingReward": "qtl.envs.rewards",
    "augment_angles": "qtl.envs.rewards",
}


def env_class(env_id: str) -> type:
    module, name = envs.ENV_IDS[env_id].split(":")
    return getattr(importlib.import_module(module), name)


def test_ids_are_registered_with_their_entry_points() -> None:
    assert set(ALL_IDS) == {
        "qtl/CartPoleSwingUp-v0",
        "qtl/MountainCar-v0",
        "qtl/Quadcopter-v0",
        "qtl/Helicopter-v0",
    }
    for env_id, entry_point in envs.ENV_IDS.items():
        assert gymnasium.spec(env_id).entry_point == entry_point


def test_envs_package_imports_nothing_else_of_qtl() -> None:
    code = "import sys, qtl.envs, gymnasium\n"
    code += "".join(f"gymnasium.make({i!r})\n" for i in ALL_IDS)
    code += "assert not [m for m in sys.modules if m.startswith('qtl.') and not m.startswith('qtl.envs')]\n"
    code += "assert 'torch' not in sys.modules\n"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_package_reexports_the_public_names() -> None:
    assert set(envs.__all__) == {*PUBLIC_NAMES, "ENV_IDS"}
    for name, module in PUBLIC_NAMES.items():
        assert getattr(envs, name) is getattr(importlib.import_module(module), name)
        assert name in dir(envs)
    with pytest.raises(AttributeError):
        _ = envs.NoSuchName
    for env_id in ALL_IDS:
        cls = env_class(env_id)
        assert getattr(envs, cls.__name__) is cls


def test_import_envs_is_lazy_about_the_env_modules() -> None:
    """`import qtl.envs` registers the ids without importing an env module, nor any of qtl but its tiny root."""
    code = "import sys, qtl.envs\n"
    code += "assert not {'qtl.envs.cartpole', 'qtl.envs.mountain_car', 'qtl.envs.aircraft'} & set(sys.modules)\n"
    code += "loaded = {m for m in sys.modules if m == 'qtl' or m.startswith('qtl.')}\n"
    code += "assert loaded == {'qtl', 'qtl.envs', 'qtl.envs.rewards'}, loaded\n"
    code += "assert 'torch' not in sys.modules\n"
    code += "from qtl.envs import CartPoleSwingUpEnv\n"
    code += "assert 'qtl.envs.cartpole' in sys.modules and 'qtl.envs.aircraft' not in sys.modules\n"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_docstring_has_the_classic_control_sections(env_id: str) -> None:
    doc = inspect.getdoc(env_class(env_id)) or ""
    headings = [line[3:].strip() for line in doc.splitlines() if line.startswith("## ")]
    assert [h for h in headings if h in DOC_SECTIONS] == list(DOC_SECTIONS), headings
    starting_state = doc.split("## Starting State", 1)[1].split("## ", 1)[0]
    assert 'reset(options={"state": ' in starting_state


@pytest.mark.parametrize("env_id", ALL_IDS)
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_check_env(env_id: str, render_mode: str | None) -> None:
    env = gymnasium.make(env_id, render_mode=render_mode)
    assert env.spec is not None and env.spec.max_episode_steps is None  # no TimeLimit wrapper
    with warnings.catch_warnings():
        # Infinite Box bounds and similar advice are warnings, not failures.
        warnings.simplefilter("ignore")
        check_env(env.unwrapped)


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_reset_determinism(env_id: str) -> None:
    env = gymnasium.make(env_id)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(N_DETERMINISM_STEPS)]

    def rollout(seed: int) -> np.ndarray:
        obs, _ = env.reset(seed=seed)
        return np.array([obs] + [env.step(a)[0] for a in actions])

    np.testing.assert_array_equal(rollout(11), rollout(11))
    assert not np.array_equal(rollout(11), rollout(12))


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_episode_contract(env_id: str) -> None:
    env = gymnasium.make(env_id).unwrapped
    obs_shape = env.observation_space.shape
    horizon = env.horizon
    assert isinstance(horizon, int) and horizon >= 1
    assert isinstance(env.reward_spec, SaturatingReward)
    assert env.reward_spec.state_dim == obs_shape[0]
    assert np.shape(env.start_mean) == obs_shape and np.shape(env.start_std) == obs_shape
    assert np.all(np.asarray(env.start_std) >= 0)

    obs, info = env.reset(seed=0)
    assert obs.shape == obs_shape and info["state"].shape == obs_shape
    action = np.zeros(env.action_space.shape)
    for t in range(1, horizon + 1):
        obs, reward, terminated, truncated, info = env.step(action)
        assert terminated is False
        assert truncated is (t == horizon)
        assert info["state"].shape == obs_shape
        assert reward == env.reward_spec(info["state"])
        assert 0.0 <= reward <= 1.0


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_render_rgb_array(env_id: str) -> None:
    env = gymnasium.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.zeros(env.action_space.shape))
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.shape[0] > 0 and frame.shape[1] > 0
    assert frame.std() > 0  # draws something


def test_render_tasks_script_covers_every_id(tmp_path: Path) -> None:
    """`scripts/render_tasks.py` writes one image and one page section per registered id."""
    script = Path(__file__).resolve().parents[2] / "scripts" / "render_tasks.py"
    subprocess.run([sys.executable, str(script), "--docs-dir", str(tmp_path)], check=True)
    page = (tmp_path / "guide" / "tasks.md").read_text(encoding="utf-8")  # the site's "The benchmark tasks"
    for env_id in ALL_IDS:
        assert f"(`{env_id}`)" in page
    images = sorted(p.name for p in (tmp_path / "img").glob("*.png"))
    assert len(images) == len(ALL_IDS)
    assert all(f"](../img/{name})" in page for name in images)  # relative to docs/guide/
