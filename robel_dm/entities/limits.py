"""Hardware-safety thresholds of a robot (ROBEL's safety counters)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class SafetyLimits:
  """Thresholds of the per-step safety counters.

  ROBEL's D'Claw thresholds: docs/robel_reference.md section 2.3.

  Attributes:
    position_margin: a joint closer than this to either end of its range
      counts as a position violation, rad.
    max_speed: a joint faster than this counts as a velocity violation, rad/s.
    max_current: a motor drawing more than this counts as a current
      violation, mA.
    position_range: which range `position_margin` refers to: 'action' (the
      actuator's control range, ROBEL's D'Claw definition) or 'joint' (the
      joint's mechanical range).
  """

  position_margin: float
  max_speed: float
  max_current: float
  position_range: str = 'action'

  def __post_init__(self):
    if self.position_range not in ('action', 'joint'):
      raise ValueError(f'position_range must be action or joint: {self}')
