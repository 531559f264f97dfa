"""The `RobotIO` of a robot on motors: what a task asks of a real robot.

The task's joint state arrives through `HardwarePhysics`; this object gives
the task the rest: the motors' measured currents, the move to an episode's
initial state, the guide motor (showing the goal, or a person setting it),
and a motion tracker's target and heading markers.
"""

import numpy as np

from robel_dm.hardware import physics as physics_lib
from robel_dm.hardware.options import (  # noqa: F401 (the modes' home)
  GUIDE_MODES,
  GUIDE_SETS_GOAL,
  GUIDE_SHOWS_GOAL,
)

# The guide's name among a robot configuration's auxiliary motors.
GUIDE_MOTOR = 'guide'


class HardwareRobotIO:
  """`RobotIO` over a `HardwarePhysics` (and its optional tracker/guide)."""

  def __init__(
    self,
    physics: physics_lib.HardwarePhysics,
    tracker=None,
    guide: str | None = None,
  ):
    """Initializes the robot's I/O.

    Args:
      physics: the attached hardware physics.
      tracker: a `tracking.TorsoTracker`, or None; its target and heading
        bodies, if it tracks them, are the task's tracked target/heading.
      guide: None, or one of `GUIDE_MODES` (the robot configuration then
        has a guide motor, which the physics reads and commands).

    Raises:
      ValueError: for an unknown guide mode.
    """
    if guide is not None and guide not in GUIDE_MODES:
      raise ValueError(f'guide must be one of {GUIDE_MODES}, got {guide!r}')
    self._physics = physics
    self._guide = guide
    has = lambda body: tracker is not None and body is not None  # noqa: E731
    self._target = (
      tracker.target_position
      if has(getattr(tracker, 'target_body', None))
      else None
    )
    self._heading = (
      tracker.heading_position
      if has(getattr(tracker, 'heading_body', None))
      else None
    )

  @property
  def motor_currents(self) -> np.ndarray:
    return self._physics.motor_currents

  def realize_initial_state(self) -> None:
    self._physics.realize_initial_state()

  def show_goal(self, goal: float) -> None:
    if self._guide == GUIDE_SHOWS_GOAL:
      self._physics.auxiliary_goals[GUIDE_MOTOR] = goal

  def goal_from_person(self) -> float | None:
    if self._guide != GUIDE_SETS_GOAL:
      return None
    return self._physics.auxiliary_angles.get(GUIDE_MOTOR)

  def tracked_target(self) -> np.ndarray | None:
    return None if self._target is None else self._target()

  def tracked_heading(self) -> np.ndarray | None:
    return None if self._heading is None else self._heading()
