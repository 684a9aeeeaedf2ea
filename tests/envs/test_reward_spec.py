"""`qtl.envs.rewards`: the declarative `SaturatingReward` spec and the `augment_angles` convention.

(Not named ``test_rewards.py``: ``tests/test_rewards.py`` exists, and pytest's default import mode
refuses two test modules with one basename in folders without ``__init__.py``.)
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from qtl.envs.rewards import SaturatingReward, augment_angles

# A 3-D state with one angle (dim 1): augmented y = [x0, x2, sin x1, cos x1].
STATE_DIM = 3
ANGLE_DIMS = (1,)
TARGET = (0.5, -0.2, 0.0, -1.0)
WEIGHT = (
    (2.0, 0.3, 0.0, 0.0),
    (0.3, 1.0, 0.1, 0.0),
    (0.0, 0.1, 0.5, 0.0),
    (0.0, 0.0, 0.0, 0.0),
)
WIDTH = 0.8


def make(**overrides: object) -> SaturatingReward:
    fields: dict[str, object] = {
        "state_dim": STATE_DIM,
        "angle_dims": ANGLE_DIMS,
        "target": TARGET,
        "weight": WEIGHT,
        "width": WIDTH,
    }
    fields.update(overrides)
    return SaturatingReward(**fields)  # type: ignore[arg-type]


# ---- construction from arrays ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("target", "weight"),
    [
        (np.array(TARGET), np.array(WEIGHT)),
        (list(TARGET), [list(row) for row in WEIGHT]),
        (tuple(np.array(TARGET)), [np.array(row) for row in WEIGHT]),
        ([np.float64(v) for v in TARGET], tuple(map(tuple, np.array(WEIGHT)))),
    ],
    ids=["ndarray", "nested-lists", "array-rows", "numpy-scalars"],
)
def test_arrays_and_sequences_give_the_tuple_spec(target: object, weight: object) -> None:
    reference = make()
    spec = make(target=target, weight=weight)
    assert spec == reference
    assert hash(spec) == hash(reference)
    assert {reference: "ok"}[spec] == "ok"  # usable as a key, interchangeably
    assert isinstance(spec.target, tuple) and all(type(v) is float for v in spec.target)
    assert isinstance(spec.weight, tuple) and all(isinstance(row, tuple) for row in spec.weight)
    assert all(type(v) is float for row in spec.weight for v in row)
    x = np.random.default_rng(0).normal(size=(7, STATE_DIM))
    np.testing.assert_array_equal(spec(x), reference(x))


def test_float32_target_is_stored_as_its_float64_values() -> None:
    spec = make(target=np.array(TARGET, dtype=np.float32))
    assert spec.target == tuple(float(v) for v in np.array(TARGET, dtype=np.float32))


def test_angle_dims_sequence_becomes_a_tuple_of_ints() -> None:
    spec = make(angle_dims=np.array([1]))
    assert spec.angle_dims == (1,) and type(spec.angle_dims[0]) is int
    assert spec == make()
    assert make(angle_dims=[1]) == make()


def test_spec_is_frozen() -> None:
    spec = make(target=np.array(TARGET))
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.target = TARGET  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.width = 1.0  # type: ignore[misc]


def test_array_input_is_copied_not_aliased() -> None:
    target = np.array(TARGET)
    spec = make(target=target)
    target[0] = 99.0
    assert spec.target == TARGET


# ---- validation ---------------------------------------------------------------------------------
@pytest.mark.parametrize("angle_dims", [(3,), (-1,), (0, 5)])
def test_angle_dim_out_of_range(angle_dims: tuple[int, ...]) -> None:
    aug = STATE_DIM + len(angle_dims)
    with pytest.raises(ValueError, match=r"angle_dims .* out of range for state_dim 3"):
        make(angle_dims=angle_dims, target=np.zeros(aug), weight=np.eye(aug))


@pytest.mark.parametrize("target", [TARGET[:3], (*TARGET, 0.0), np.zeros((4, 1)), np.zeros((1, 4))])
def test_wrong_target_length(target: object) -> None:
    with pytest.raises(ValueError, match=r"target has shape .*augmented state has length 4"):
        make(target=target)


@pytest.mark.parametrize("weight", [np.eye(3), np.eye(5), np.ones(4), np.ones((4, 3)), np.ones((1, 4, 4))])
def test_wrong_weight_shape(weight: np.ndarray) -> None:
    with pytest.raises(ValueError, match=r"weight has shape .*expected \(4, 4\)"):
        make(weight=weight)


def test_weight_must_be_symmetric() -> None:
    weight = np.array(WEIGHT)
    weight[0, 1] += 0.2
    with pytest.raises(ValueError, match="symmetric positive semi-definite"):
        make(weight=weight)


def test_weight_must_be_positive_semi_definite() -> None:
    weight = np.diag([1.0, 1.0, -0.5, 0.0])
    with pytest.raises(ValueError, match="symmetric positive semi-definite"):
        make(weight=weight)


def test_rank_deficient_psd_weight_is_accepted() -> None:
    c = np.array([[1.0, 0.0, 0.6, 0.0]])
    assert make(weight=c.T @ c).weight_matrix.shape == (4, 4)


@pytest.mark.parametrize("width", [0.0, -0.25, float("nan")])
def test_width_must_be_positive(width: float) -> None:
    with pytest.raises(ValueError, match="width must be positive"):
        make(width=width)


# ---- augment_angles -------------------------------------------------------------------------------
def test_augment_angles_orders_non_angle_dims_then_sin_cos_per_angle() -> None:
    x = np.array([0.1, 0.2, 0.3, 0.4])
    y = augment_angles(x, (2, 0))  # angles in the order given, not sorted
    expected = [0.2, 0.4, math.sin(0.3), math.cos(0.3), math.sin(0.1), math.cos(0.1)]
    np.testing.assert_allclose(y, expected, rtol=0, atol=0)


def test_augment_angles_without_angles_is_the_identity() -> None:
    x = np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(augment_angles(x, ()), x)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_augment_angles_batch_shapes(batch: tuple[int, ...]) -> None:
    x = np.random.default_rng(1).normal(size=(*batch, 4))
    y = augment_angles(x, (1, 3))
    assert y.shape == (*batch, 6)
    flat = y.reshape(-1, 6)
    for row_x, row_y in zip(x.reshape(-1, 4), flat, strict=True):
        np.testing.assert_array_equal(row_y, augment_angles(row_x, (1, 3)))


# ---- the reward itself ----------------------------------------------------------------------------
def test_reward_is_one_at_the_target_and_a_float_for_one_state() -> None:
    spec = make()
    r = spec(np.array([0.5, math.pi, -0.2]))  # sin π ≈ 0, cos π = −1: the target
    assert isinstance(r, float)
    assert r == pytest.approx(1.0, abs=1e-12)


def test_reward_value_matches_the_quadratic_form() -> None:
    spec = make()
    x = np.array([0.1, 0.7, 0.3])
    y = np.array([0.1, 0.3, math.sin(0.7), math.cos(0.7)]) - np.array(TARGET)
    expected = math.exp(-0.5 * y @ np.array(WEIGHT) @ y / WIDTH**2)
    assert spec(x) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("batch", [(5,), (2, 3)])
def test_reward_batch_shapes(batch: tuple[int, ...]) -> None:
    spec = make()
    x = np.random.default_rng(2).normal(size=(*batch, STATE_DIM))
    r = spec(x)
    assert isinstance(r, np.ndarray) and r.shape == batch
    assert np.all((r > 0) & (r <= 1))
    np.testing.assert_allclose(r.reshape(-1), [spec(row) for row in x.reshape(-1, STATE_DIM)], rtol=1e-12)
