"""How a robot gets to an episode's initial state on hardware.

A reset procedure is called with the robot, the clock and the initial state
the task chose (joint angles in action order, and goals for auxiliary motors
such as the D'Claw's valve); it must leave the actuated joints torqued at
that state and the auxiliary motors released. Every procedure is bounded in
time and attempts and raises `ResetError`, naming the motors, when it fails.

* `MoveReset` ('move'): one bounded blocking move (ROBEL's plain reset).
* `DClawScriptedReset` ('scripted'): ROBEL's D'Claw reset (robel_facts 4.4):
  fingers relaxed while the valve is driven to its initial angle, then the
  claw moved with a check per motor, and a disentangling sequence between
  retries.
* `ManualReset` ('manual'): the motors are released, a person places the
  robot, then a blocking move.
"""

from collections.abc import Callable
import logging

import numpy as np

from robel_dm.hardware import clock as clock_lib
from robel_dm.hardware import robot as robot_lib

# Blocking moves (robel_facts 4.3): the move ends when every checked joint is
# within the tolerance, when none moved more than the stall tolerance for two
# polls, or at the timeout.
MOVE_TOLERANCE = np.deg2rad(1.0)  # rad
MOVE_STALL_TOLERANCE = np.deg2rad(1.0)  # rad per poll
MOVE_STALL_POLLS = 2
MOVE_POLL_INTERVAL = 0.25  # s
MOVE_TIMEOUT = 3.0  # s
# A joint still off by more than this after a plain move is reported, rad
# (ROBEL's "good reset" tolerance).
GOOD_RESET_TOLERANCE = np.deg2rad(5.0)

# ROBEL's scripted D'Claw reset (robel_facts 4.4).
_MIN_CLAW_RESET_TIME = 1.0  # s, from relaxing the fingers to moving them.
_VALVE_MOVE_TIMEOUT = 10.0  # s
_MAX_CLAW_ATTEMPTS = 4  # The first try and ROBEL's 3 retries.
_DISENTANGLE_STEP = 0.75  # s
_DISENTANGLE_TOP_POSE = np.pi / 4  # rad, top joints while disentangling.


class ResetError(RuntimeError):
  """A reset failed; `motor_ids` names the motors that did not get there."""

  def __init__(self, message: str, motor_ids=()):
    super().__init__(message)
    self.motor_ids = tuple(motor_ids)


def move(
  robot: robot_lib.HardwareRobot,
  clock: clock_lib.Clock,
  joint_goals: np.ndarray,
  auxiliary_goals: dict[str, float] | None = None,
  timeout: float = MOVE_TIMEOUT,
) -> np.ndarray:
  """Commands goals and waits until the motors get there, stall or time out.

  Motors with torque off ignore their goals (their error still counts).

  Returns:
    |error| of every motor (joints, then auxiliaries), rad.
  """
  auxiliary_goals = auxiliary_goals or {}
  desired = np.array(robot.positions)
  desired[: len(joint_goals)] = joint_goals
  for name, goal in auxiliary_goals.items():
    desired[robot.auxiliary_index(name)] = goal
  checked = np.zeros(len(desired), bool)
  checked[: len(joint_goals)] = True
  for name in auxiliary_goals:
    checked[robot.auxiliary_index(name)] = True
  deadline = clock.now() + timeout
  robot.read()
  previous, stalled = robot.positions.copy(), 0
  while True:
    robot.write_joint_goals(joint_goals)
    for name, goal in auxiliary_goals.items():
      robot.write_auxiliary_goal(name, goal)
    clock.sleep_until(clock.now() + MOVE_POLL_INTERVAL)
    robot.read()
    error = np.where(checked, np.abs(robot.positions - desired), 0.0)
    moved = np.abs(robot.positions - previous).max()
    previous[:] = robot.positions
    stalled = stalled + 1 if moved < MOVE_STALL_TOLERANCE else 0
    if (
      error.max() <= MOVE_TOLERANCE
      or stalled >= MOVE_STALL_POLLS
      or clock.now() >= deadline
    ):
      return error


def _release_auxiliaries(robot: robot_lib.HardwareRobot) -> None:
  if robot.auxiliary:
    robot.set_torque(False, [motor.id for motor in robot.auxiliary])


class MoveReset:
  """One bounded blocking move of every motor, then auxiliaries released."""

  name = 'move'

  def __call__(self, robot, clock, joint_goals, auxiliary_goals) -> None:
    robot.set_torque(True)
    error = move(robot, clock, joint_goals, auxiliary_goals)
    off = error > GOOD_RESET_TOLERANCE
    if off.any():
      logging.warning(
        'reset: motors %s stopped %s rad from the initial pose',
        np.asarray(robot.motor_ids)[off].tolist(),
        np.round(error[off], 3).tolist(),
      )
    _release_auxiliaries(robot)


class DClawScriptedReset:
  """ROBEL's scripted D'Claw reset, bounded: see the module docstring."""

  name = 'scripted'

  def __init__(self, top, middle, bottom, max_attempts=_MAX_CLAW_ATTEMPTS):
    """Initializes the reset.

    Args:
      top: IDs of the three top (J?0) motors.
      middle: IDs of the middle (J?1) motors.
      bottom: IDs of the bottom (J?2) motors.
      max_attempts: claw moves before giving up (ROBEL: 1 + 3 retries).
    """
    self._top, self._middle, self._bottom = (
      tuple(top),
      tuple(middle),
      tuple(bottom),
    )
    self._max_attempts = max_attempts

  def __call__(self, robot, clock, joint_goals, auxiliary_goals) -> None:
    start = clock.now()
    # 1. Relax the top and bottom joints and aim the claw at its goal, so
    # the fingers let go of the valve.
    robot.set_torque(False, self._top + self._bottom)
    robot.set_torque(True, self._middle)
    robot.write_joint_goals(joint_goals)
    # 2. Drive the valve (and guide) to their initial angles.
    if auxiliary_goals:
      robot.set_torque(True, [m.id for m in robot.auxiliary])
      error = move(
        robot, clock, joint_goals, auxiliary_goals, _VALVE_MOVE_TIMEOUT
      )
      stuck = [
        name
        for name in auxiliary_goals
        if error[robot.auxiliary_index(name)] > GOOD_RESET_TOLERANCE
      ]
      if stuck:
        raise ResetError(f'reset: the {stuck} motor did not reach its angle')
    clock.sleep_until(start + _MIN_CLAW_RESET_TIME)
    # 3-4. Move the claw; disentangle and retry while a finger is off.
    claw = robot.joint_ids
    for attempt in range(1, self._max_attempts + 1):
      robot.set_torque(True, claw)
      error = move(robot, clock, joint_goals)[: len(claw)]
      off = [motor for motor, e in zip(claw, error, strict=True)
             if e > GOOD_RESET_TOLERANCE]  # fmt: skip
      if not off:
        break
      logging.warning(
        'reset attempt %d: claw motors %s are off the reset pose by %s rad',
        attempt,
        off,
        np.round(error[error > GOOD_RESET_TOLERANCE], 3).tolist(),
      )
      if attempt < self._max_attempts:
        self._disentangle(robot, clock, joint_goals)
    else:
      raise ResetError(
        f'reset: claw motors {off} did not reach the reset pose within 5 '
        f'degrees in {self._max_attempts} attempts; is a finger stuck or '
        'entangled?',
        off,
      )
    _release_auxiliaries(robot)

  def _disentangle(self, robot, clock, joint_goals) -> None:
    """ROBEL's sequence: all limp, then top, middle, bottom in turn."""
    robot.set_torque(False, robot.joint_ids)
    clock.sleep_until(clock.now() + _DISENTANGLE_STEP)
    goals = np.array(robot.positions)[: len(joint_goals)]
    for group, pose in (
      (self._top, _DISENTANGLE_TOP_POSE),
      (self._middle, None),
      (self._bottom, None),
    ):
      for motor_id in group:
        index = robot.joint_ids.index(motor_id)
        goals[index] = joint_goals[index] if pose is None else pose
      robot.write_joint_goals(goals)
      robot.set_torque(True, group)
      clock.sleep_until(clock.now() + _DISENTANGLE_STEP)


class ManualReset:
  """Releases the motors, waits for a person to place the robot, then moves.

  `wait` is called with instructions and returns when the robot is in place
  (by default it asks for Enter on the terminal).
  """

  name = 'manual'

  def __init__(self, wait: Callable[[str], object] = input):
    self._wait = wait

  def __call__(self, robot, clock, joint_goals, auxiliary_goals) -> None:
    robot.set_torque(False)
    self._wait(
      'Motors released. Put the robot near its initial pose, keep clear, and '
      'press Enter to continue.'
    )
    MoveReset()(robot, clock, joint_goals, auxiliary_goals)


def make(name, robot_config, domain: str):
  """The reset procedure `name` for a robot.

  Args:
    name: 'scripted', 'move' or 'manual'; or a procedure (a callable with the
      signature of `MoveReset.__call__`), returned as is.
    robot_config: the robot's configuration (for motor groups).
    domain: 'dclaw' or 'dkitty'.

  Raises:
    ValueError: for an unknown name or one the robot does not support.
  """
  if callable(name):
    return name
  if name == 'move':
    return MoveReset()
  if name == 'manual':
    return ManualReset()
  if name == 'scripted':
    if domain == 'dclaw':
      return DClawScriptedReset(
        robot_config.group('top'),
        robot_config.group('middle'),
        robot_config.group('bottom'),
      )
    raise ValueError(
      f"the scripted {domain} reset is not available yet; use reset='move' "
      "or 'manual'"
    )
  raise ValueError(
    f"unknown reset {name!r}; expected 'scripted', 'move' or 'manual'"
  )
