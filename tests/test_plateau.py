"""MC-PILCO's plateau rule: the change statistics' recursions, when a plateau is (and is not) reported, annealing."""

from __future__ import annotations

import math

import pytest
import torch

from qtl.plateau import MIN_THRESHOLD, PlateauMonitor, PlateauRule

DTYPE = torch.float64


def noise(steps: int, seed: int, scale: float = 1.0) -> list[float]:
    """``steps`` standard normal draws × ``scale``, from a seeded generator."""
    return (scale * torch.randn(steps, generator=torch.Generator().manual_seed(seed), dtype=DTYPE)).tolist()


def first_plateau(monitor: PlateauMonitor, values: list[float]) -> int | None:
    """The monitor's step count at the first update that reports a plateau (None: none in ``values``)."""
    for value in values:
        if monitor.update(value):
            return monitor.step
    return None


def reference(values: list[float], rule: PlateauRule) -> tuple[list[float], list[bool]]:
    """ρ after each of V_1, V_2, … and the plateau decisions, written out from MC-PILCO's recursions (V_0 first).

    d_t = V_t − V_{t−1}; m_t = a m_{t−1} + (1 − a) d_t; s²_t = a (s²_{t−1} + (1 − a)(d_t − m_{t−1})²);
    ρ_t = a ρ_{t−1} + (1 − a) m_t / s_t (ρ unchanged while s = 0); a plateau at step t > min_steps when
    |ρ| < threshold at each of the last ``window`` steps.
    """
    a = rule.ema
    m = s2 = rho = 0.0
    ratios, decisions = [], []
    for t in range(1, len(values)):
        d = values[t] - values[t - 1]
        m_new = a * m + (1 - a) * d
        s2 = a * (s2 + (1 - a) * (d - m) ** 2)
        m = m_new
        if s2 > 0:
            rho = a * rho + (1 - a) * m / math.sqrt(s2)
        ratios.append(rho)
        recent = ratios[-rule.window:]
        decisions.append(t > rule.min_steps and len(recent) == rule.window
                         and all(abs(r) < rule.threshold for r in recent))
    return ratios, decisions


def test_ratio_and_decisions_follow_the_recursions():
    """A rising stretch, a flat noisy one, a rising one: ρ and every decision as the written-out recursions give."""
    rule = PlateauRule(ema=0.9, threshold=0.08, window=15, min_steps=20)
    steps = torch.arange(300, dtype=DTYPE)
    trend = torch.where(steps < 100, 0.05 * steps, torch.where(steps < 200, 5.0, 5.0 + 0.05 * (steps - 200)))
    values = (trend + torch.tensor(noise(300, seed=1, scale=0.1), dtype=DTYPE)).tolist()
    want_ratios, want_decisions = reference(values, rule)
    monitor = PlateauMonitor(rule, values[0])
    ratios, decisions = [], []
    for value in values[1:]:
        decisions.append(monitor.update(value))
        ratios.append(monitor.ratio)
    assert ratios == pytest.approx(want_ratios, rel=1e-12, abs=1e-15)
    assert decisions == want_decisions
    assert any(decisions[100:200]) and not any(decisions[:100])  # the flat stretch, and only it, plateaus
    assert monitor.step == 299


def test_a_steadily_rising_objective_never_plateaus():
    rule = PlateauRule(ema=0.99, threshold=0.08, window=50, min_steps=50)
    values = [0.01 * t + v for t, v in enumerate(noise(2001, seed=2, scale=0.01))]
    monitor = PlateauMonitor(rule, values[0])
    assert first_plateau(monitor, values[1:]) is None
    assert monitor.step == 2000 and monitor.ratio > 0.5  # ΔV well above its noise: ρ far from the threshold


@pytest.mark.parametrize(("window", "min_steps"), [(50, 200), (60, 10), (30, 0)])
def test_a_flat_noisy_objective_plateaus_but_not_before_min_steps_and_a_window(window, min_steps):
    rule = PlateauRule(ema=0.99, threshold=0.08, window=window, min_steps=min_steps)
    values = noise(2000, seed=3)
    found = first_plateau(PlateauMonitor(rule, values[0]), values[1:])
    assert found is not None and max(min_steps + 1, window) <= found <= max(min_steps + 1, window) + 3 * window


@pytest.mark.parametrize(("window", "min_steps"), [(5, 20), (25, 10), (1, 0)])
def test_a_constant_objective_plateaus_at_the_first_step_allowed(window, min_steps):
    """ΔV = 0: s = 0, ρ stays 0, so the plateau comes exactly at step max(min_steps + 1, window)."""
    monitor = PlateauMonitor(PlateauRule(window=window, min_steps=min_steps), 1.0)
    assert first_plateau(monitor, [1.0] * 200) == max(min_steps + 1, window)
    assert monitor.ratio == 0.0


def test_annealing_halves_the_threshold_and_waits_a_window():
    rule = PlateauRule(ema=0.99, threshold=0.08, window=10, min_steps=5)
    monitor = PlateauMonitor(rule, 0.0)
    plateaus = []
    for _ in range(5):
        plateaus.append(first_plateau(monitor, [0.0] * 100))
        monitor.annealed()
        assert monitor.next_decision == monitor.step + rule.window
    # The first at step 10 (a full window), then each exactly `window` updates after the last, reported on the next.
    assert plateaus == [10, 21, 32, 43, 54]
    assert monitor.threshold == MIN_THRESHOLD == 0.01  # 0.08 → 0.04 → 0.02 → 0.01, and not below
    assert rule.threshold == 0.08  # the settings are not changed


def test_annealed_threshold_is_the_one_used():
    """|ρ| held at 0.06 (ΔV = 0 leaves ρ as it is): a plateau under 0.08, none under the annealed 0.04."""
    monitor = PlateauMonitor(PlateauRule(ema=0.5, threshold=0.08, window=5, min_steps=0), 0.0)
    monitor._ratio = 0.06  # a steady ratio, set directly
    assert first_plateau(monitor, [0.0] * 50) == 5
    monitor.annealed()
    assert monitor.threshold == 0.04 and first_plateau(monitor, [0.0] * 50) is None
    assert monitor.ratio == 0.06


@pytest.mark.parametrize("settings", [
    {"ema": 0.0}, {"ema": 1.0}, {"ema": -0.5}, {"threshold": 0.0}, {"threshold": -0.1}, {"window": 0},
    {"min_steps": -1},
])
def test_bad_settings_are_refused(settings):
    with pytest.raises(ValueError, match="plateau rule needs"):
        PlateauRule(**settings)
