"""Learning under a safety budget: ROBEL's violations priced by a learned
Lagrange multiplier (see `robel_dm.learning.sac`, which applies it)."""

import dataclasses

import numpy as np


@dataclasses.dataclass
class SafetyConstraint:
  """A budget of safety violations per episode and its Lagrange multiplier.

  Attributes:
    budget: violations per episode (position, velocity and current counts
      summed) the policy may make.
    learning_rate: the multiplier's step per training episode, per budget
      of excess (an episode at twice the budget raises it by this much).
    multiplier: the price of one violation in reward units (learned).
    max_multiplier: the multiplier's ceiling.
  """

  budget: float
  learning_rate: float = 0.05
  multiplier: float = 0.0
  max_multiplier: float = 100.0
  _episode_violations: np.ndarray | None = None

  def __post_init__(self):
    if not self.budget >= 0:  # Also NaN.
      raise ValueError(f'the safety budget must be >= 0, got {self.budget}')

  def observe(self, violations: np.ndarray, dones: np.ndarray) -> None:
    """Counts a step's violations per environment; at an episode's end,
    moves the multiplier by that episode's excess over the budget."""
    if self._episode_violations is None:
      self._episode_violations = np.zeros(len(violations))
    self._episode_violations += violations
    for total in self._episode_violations[dones]:
      self.end_episode(total)
    self._episode_violations[dones] = 0.0

  def end_episode(self, total: float) -> None:
    """Moves the multiplier by the excess over the budget of one finished
    episode that made `total` violations (all kinds summed)."""
    # Relative to the budget, and bounded: one wild early episode (Pose
    # counts hundreds) must not throw the multiplier to its ceiling.
    excess = np.clip((total - self.budget) / max(self.budget, 1.0), -1, 10)
    self.multiplier = float(
      np.clip(
        self.multiplier + self.learning_rate * excess,
        0.0,
        self.max_multiplier,
      )
    )


def step_violations(infos) -> np.ndarray:
  """Each environment's safety violations in one step (all kinds)."""
  return np.array([sum(info['safety'].values()) for info in infos], np.float32)
