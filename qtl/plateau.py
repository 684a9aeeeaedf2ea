"""MC-PILCO's plateau rule for a stochastic policy search: when the objective stops moving, anneal, then stop.

Amadio et al. 2022 (MC-PILCO), Sec. V-B: with d_t = V_t − V_{t−1} the change of the (noisy) objective
between steps, exponential moving averages with factor a give its mean m and variance s², and a
smoothed signal-to-noise ratio ρ_{t+1} = a ρ_t + (1 − a) m_{t+1} / s. When |ρ| stays below a threshold
for ``window`` consecutive steps (after ``min_steps``), the search is on a plateau: the schedule
lowers the learning rate and the policy dropout (and halves the threshold); on a plateau at the
lowest learning rate it stops.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

# The threshold is halved at every plateau, down to this.
MIN_THRESHOLD = 0.01


@dataclass
class PlateauRule:
    """The settings: EMA factor a, threshold on |ρ|, ``window`` steps below it, no decision before ``min_steps``."""

    ema: float = 0.99
    threshold: float = 0.08
    window: int = 200
    min_steps: int = 200

    def __post_init__(self) -> None:
        if not 0.0 < self.ema < 1.0 or self.threshold <= 0 or self.window < 1 or self.min_steps < 0:
            raise ValueError(
                f"plateau rule needs 0 < ema < 1, threshold > 0, window >= 1 and min_steps >= 0; got ema={self.ema}, "
                f"threshold={self.threshold}, window={self.window}, min_steps={self.min_steps}"
            )


class PlateauMonitor:
    """Feeds on the objective's values step by step; says when the search has reached a plateau."""

    def __init__(self, rule: PlateauRule, first_value: float) -> None:
        self.rule = rule
        self.threshold = rule.threshold
        self.next_decision = rule.min_steps
        self.step = 0
        self._previous = first_value
        self._mean = 0.0  # m: EMA of d_t
        self._var = 0.0  # s²: EMA of (d_t − m)²
        self._ratio = 0.0  # ρ
        self._recent: deque[float] = deque(maxlen=rule.window)

    @property
    def ratio(self) -> float:
        """ρ, the smoothed signal-to-noise ratio of the objective's change."""
        return self._ratio

    def update(self, value: float) -> bool:
        """Take V_t; True when |ρ| has stayed below the threshold for ``window`` steps past the next decision step."""
        a = self.rule.ema
        change = value - self._previous
        previous_mean = self._mean
        self._mean = a * self._mean + (1 - a) * change
        self._var = a * (self._var + (1 - a) * (change - previous_mean) ** 2)
        if self._var > 0:
            self._ratio = a * self._ratio + (1 - a) * self._mean / math.sqrt(self._var)
        self._previous = value
        self._recent.append(abs(self._ratio))
        self.step += 1
        full = len(self._recent) == self.rule.window
        return self.step > self.next_decision and full and max(self._recent) < self.threshold

    def annealed(self) -> None:
        """After a plateau: the threshold halves (not below MIN_THRESHOLD); the next decision waits ``window`` steps."""
        self.threshold = max(self.threshold / 2, MIN_THRESHOLD)
        self.next_decision = self.step + self.rule.window
