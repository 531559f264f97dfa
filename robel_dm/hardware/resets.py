"""How a robot gets to an episode's initial state on hardware.

A reset procedure is called with the robot, the clock and the initial state
the task chose (joint angles in action order, and goals for auxiliary motors
such as the D'Claw's valve); it must leave the actuated joints torqued at
that state and the auxiliary motors released. Every procedure is bounded in
time and attempts. A procedure raises `ResetError` when it cannot go on (a
finger or the valve that does not get there, a D'Kitty that does not stand
up), naming the motors where motors are at fault; a plain move that ends
short of the pose logs the motors and how far they are off, and the episode
starts where they stopped, as in ROBEL.

* `MoveReset` ('move'): one bounded blocking move (ROBEL's plain reset).
* `DClawScriptedReset` ('scripted'): ROBEL's D'Claw reset
  (docs/robel_reference.md section 4.4):
  fingers relaxed while the valve is driven to its initial angle, then the
  claw moved with a check per motor, and a disentangling sequence between
  retries.
* `ManualReset` ('manual'): the motors are released, a person places the
  robot, then a blocking move.
"""

from collections.abc import Callable
import logging

import numpy as np

from robel_dm import geometry
from robel_dm.hardware import clock as clock_lib
from robel_dm.hardware import robot as robot_lib

# Blocking moves (docs/robel_reference.md section 4.3): the move ends when every
# checked joint is within the tolerance, when none moved more than the stall
# tolerance for two polls, or at the timeout.
MOVE_TOLERANCE = np.deg2rad(1.0)  # rad
MOVE_STALL_TOLERANCE = np.deg2rad(1.0)  # rad per poll
MOVE_STALL_POLLS = 2
MOVE_POLL_INTERVAL = 0.25  # s
MOVE_TIMEOUT = 3.0  # s
# A joint still off by more than this after a plain move is reported, rad
# (ROBEL's "good reset" tolerance).
GOOD_RESET_TOLERANCE = np.deg2rad(5.0)

# ROBEL's scripted D'Claw reset (docs/robel_reference.md section 4.4).
_MIN_CLAW_RESET_TIME = 1.0  # s, from relaxing the fingers to moving them.
_VALVE_MOVE_TIMEOUT = 10.0  # s
_MAX_CLAW_ATTEMPTS = 4  # The first try and ROBEL's 3 retries.
_DISENTANGLE_STEP = 0.75  # s
# rad, top joints while disentangling: beyond their range (+-0.48 rad), so
# the goal stops at its end (27.5 degrees), as ROBEL's clip to the range does.
_DISENTANGLE_TOP_POSE = np.pi / 4

# ROBEL's "manual-auto" D'Kitty reset: poll the tracker (s), require more
# than this many consecutive good checks, then wait (s); robel_dm gives up
# after the timeout (s).
_MANUAL_POLL_INTERVAL = 0.1
_MANUAL_GOOD_CHECKS = 5
_MANUAL_SETTLE = 1.0
_MANUAL_TIMEOUT = 120.0


class ResetError(RuntimeError):
  """A reset failed; `motor_ids` names the motors that did not get there
  (empty where no motor is at fault, e.g. a D'Kitty that did not stand)."""

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
        ids = [robot.auxiliary_id(name) for name in stuck]
        raise ResetError(
          f'reset: the {", ".join(stuck)} motor (ID '
          f'{", ".join(map(str, ids))}) did not reach its angle within 5 '
          'degrees',
          ids,
        )
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

  Without a torso source, `wait` is called with instructions and returns
  when the robot is in place (by default it asks for Enter on the
  terminal). With one (a D'Kitty with a tracker), the reset instead waits
  until the torso has been upright and no higher than standing for more
  than 5 checks 0.1 s apart, then 1 s more (ROBEL's ManualAuto), and fails
  after `timeout` seconds. On a simulated robot, `operator` is the person:
  called once the motors are released, it puts the robot in place, and the
  move follows at once.
  """

  name = 'manual'

  def __init__(
    self,
    wait: Callable[[str], object] = input,
    torso_source=None,
    timeout: float = _MANUAL_TIMEOUT,
    operator: Callable[[], None] | None = None,
  ):
    self._wait = wait
    self._torso = torso_source
    self._timeout = timeout
    self._operator = operator

  def __call__(self, robot, clock, joint_goals, auxiliary_goals) -> None:
    robot.set_torque(False)
    message = (
      'Motors released. Put the robot near its initial pose, keep clear, and '
      'press Enter to continue.'
    )
    if self._operator is not None:
      # Placed at once and held there until the move below takes over:
      # limp legs would otherwise fold under it.
      self._operator()
    elif self._torso is None:
      self._wait(message)
    else:
      logging.warning('Motors released: stand the robot up.')
      self._wait_until_upright(clock)
    MoveReset()(robot, clock, joint_goals, auxiliary_goals)

  def _wait_until_upright(self, clock) -> None:
    deadline = clock.now() + self._timeout
    good = 0
    while good <= _MANUAL_GOOD_CHECKS:
      if clock.now() > deadline:
        upright, height = upright_and_height(self._torso)
        raise ResetError(
          f'manual reset: the robot was not stood up within {self._timeout} s '
          f'(upright {upright:.2f}, torso height {height:.2f} m)'
        )
      clock.sleep_until(clock.now() + _MANUAL_POLL_INTERVAL)
      upright, height = upright_and_height(self._torso)
      upright_enough = upright >= _UPRIGHT_THRESHOLD
      low_enough = height <= _STANDING_HEIGHT + _HEIGHT_TOLERANCE
      good = good + 1 if upright_enough and low_enough else 0
    clock.sleep_until(clock.now() + _MANUAL_SETTLE)


def make(
  procedure, robot_config, domain: str, torso_source=None, operator=None
):
  """The reset procedure `procedure` names, for the robot `domain`.

  Args:
    procedure: 'scripted', 'move' or 'manual'; or a procedure (a callable
      with the signature of `MoveReset.__call__`), returned as is.
    robot_config: the robot's configuration (for motor groups).
    domain: the robot: 'dclaw' or 'dkitty' (the robots with a scripted
      reset).
    torso_source: the D'Kitty's torso pose (for its scripted reset).
    operator: for 'manual' on a simulated robot, the simulated person
      (see `ManualReset`).

  Raises:
    ValueError: for an unknown procedure or one the robot does not support.
  """
  if callable(procedure):
    return procedure
  if procedure == 'move':
    return MoveReset()
  if procedure == 'manual':
    return ManualReset(torso_source=torso_source, operator=operator)
  if procedure != 'scripted':
    raise ValueError(
      f"unknown reset {procedure!r}; expected 'scripted', 'move' or 'manual'"
    )
  if domain == 'dclaw':
    return DClawScriptedReset(
      robot_config.group('top'),
      robot_config.group('middle'),
      robot_config.group('bottom'),
    )
  if domain != 'dkitty':
    raise ValueError(
      f"robot {domain!r} has no scripted reset; use 'move' or 'manual'"
    )
  if torso_source is None:
    raise ValueError(
      'the scripted dkitty reset needs the torso pose (a tracker)'
    )
  return DKittyScriptedReset(
    torso_source,
    robot_config.group('left'),
    robot_config.group('right'),
    robot_config.group('front'),
    robot_config.group('back'),
  )


# ROBEL's scripted D'Kitty stand-up (docs/robel_reference.md section 4.5). Joint
# angles per pair of legs (the group's two legs in ID order), rad; beyond the
# action ranges on purpose (reset moves are not clipped to them); limits in
# the robot configuration refuse the sequence before it starts.
_TUCK_SPAN = 2.4
_FOOT_SPAN = 2.5
_INWARD_TUCK = np.array(
  [0, _TUCK_SPAN, -_FOOT_SPAN, 0, -_TUCK_SPAN, _FOOT_SPAN]
)
_UPRIGHT_THRESHOLD = 0.9
_STANDING_HEIGHT = 0.30  # m, torso height standing on robel_dm's model.
_HEIGHT_TOLERANCE = 0.05  # m
_MAX_STAND_ATTEMPTS = 5
_MAX_FLIP_ATTEMPTS = 3
_POSE_TOLERANCE = np.deg2rad(5.0)  # rad
_POSE_STALL_TOLERANCE = np.deg2rad(0.1)  # rad per poll


def _pair(triple) -> np.ndarray:
  return np.tile(triple, 2)


def upright_and_height(torso_source) -> tuple[float, float]:
  """The torso's uprightness (cosine of its tilt) and height, m."""
  position, quaternion, _, _ = torso_source()
  return geometry.upright(quaternion), float(position[2])


class DKittyScriptedReset:
  """ROBEL's D'Kitty stand-up sequence, bounded.

  ROBEL's sequence: docs/robel_reference.md section 4.5.

  Needs the torso pose (a tracker, or the virtual bus's simulation). While
  the robot is not standing: if upside down, flip it over; tuck the legs
  under the body; stand up. Then the task's initial pose is moved to.
  Standing means upright >= 0.9 at robel_dm's standing height (0.30 m;
  ROBEL's tracker measured 0.35). On the simulated robot the sequence gets
  up from a crouch, but ROBEL's flip does not right it from its back; after
  5 attempts the reset fails with an error.
  """

  name = 'scripted'

  def __init__(self, torso_source, left, right, front, back):
    self._torso = torso_source
    self._left, self._right = tuple(left), tuple(right)
    self._front, self._back = tuple(front), tuple(back)

  def standing(self) -> bool:
    upright, height = upright_and_height(self._torso)
    return (
      upright >= _UPRIGHT_THRESHOLD
      and abs(height - _STANDING_HEIGHT) <= _HEIGHT_TOLERANCE
    )

  def __call__(self, robot, clock, joint_goals, auxiliary_goals) -> None:
    self._check_limits(robot)
    robot.set_torque(True)
    for attempt in range(1, _MAX_STAND_ATTEMPTS + 1):
      if self.standing():
        break
      logging.info('stand-up attempt %d', attempt)
      self._flip_if_upside_down(robot, clock)
      self._tuck(robot, clock)
      self._stand_up(robot, clock)
    else:
      if not self.standing():
        upright, height = upright_and_height(self._torso)
        raise ResetError(
          f"the D'Kitty did not stand up in {_MAX_STAND_ATTEMPTS} attempts "
          f'(upright {upright:.2f}, torso height {height:.2f} m)'
        )
    MoveReset()(robot, clock, joint_goals, auxiliary_goals)

  def _check_limits(self, robot) -> None:
    """Refuses, before anything moves, a sequence that would take a joint
    beyond the limits of the robot's configuration."""
    poses = [self._flat_pose(), *self._roll_poses(), *self._tuck_poses()]
    poses += self._stand_poses()
    for groups, _ in poses:
      for ids, angles in groups.items():
        try:
          robot.check_configured_limits(ids, angles)
        except ValueError as error:
          raise ResetError(
            f"the D'Kitty's scripted reset cannot run: {error} (widen the "
            "limits in the robot configuration, or use reset='move' or "
            "'manual')"
          ) from None

  def _pose(self, robot, clock, groups: dict, seconds: float) -> None:
    """Commands joint angles to groups of motors and waits (bounded)."""
    for ids, angles in groups.items():
      robot.write_reset_goals(ids, angles)
    deadline = clock.now() + seconds
    previous = None
    while clock.now() < deadline:
      clock.sleep_until(min(deadline, clock.now() + MOVE_POLL_INTERVAL))
      robot.read()
      errors = [
        np.abs(robot.positions_of(ids) - angles).max()
        for ids, angles in groups.items()
      ]
      if max(errors) <= _POSE_TOLERANCE:
        return
      if previous is not None and (
        np.abs(robot.positions - previous).max() < _POSE_STALL_TOLERANCE
      ):
        return
      previous = robot.positions.copy()

  def _flat_pose(self) -> tuple[dict, float]:
    """Legs spread flat to the sides: where flipping and tucking start."""
    left = _INWARD_TUCK.copy()
    left[[0, 3]] = np.pi / 2
    right = _INWARD_TUCK.copy()
    right[[0, 3]] = -np.pi / 2
    return {self._left: left, self._right: right}, 4.0

  def _roll_poses(self) -> list[tuple[dict, float]]:
    """A roll from the back onto the legs."""
    return [
      ({
        self._left: _pair([-np.pi / 4, -_TUCK_SPAN, _FOOT_SPAN]),
        self._right: _pair([-5 * np.pi / 4, 0, 0]),
      }, 4.0),
      ({
        self._left: _pair([np.pi / 2, 0, 0]),
        self._right: _pair([-np.pi / 2, 0, 0]),
      }, 4.0),
    ]  # fmt: skip

  def _tuck_poses(self) -> list[tuple[dict, float]]:
    return [
      ({self._left: _INWARD_TUCK}, 4.0),
      ({self._right: _INWARD_TUCK}, 4.0),
    ]

  def _stand_poses(self) -> list[tuple[dict, float]]:
    everything = self._left + self._right
    ids = tuple(np.asarray(everything)[np.argsort(everything)])
    standing = np.zeros(len(everything))
    return [
      ({self._back: _pair([0, _TUCK_SPAN, -_FOOT_SPAN])}, 4.0),
      ({self._front: _pair([0, -_TUCK_SPAN, _FOOT_SPAN])}, 4.0),
      ({ids: standing}, 3.0),
      ({ids: np.tile([0, np.pi / 6, -np.pi / 6], 4)}, 1.0),
      ({ids: standing}, 3.0),
    ]

  def _flatten(self, robot, clock) -> None:
    self._pose(robot, clock, *self._flat_pose())

  def _flip_if_upside_down(self, robot, clock) -> None:
    for _ in range(_MAX_FLIP_ATTEMPTS):
      if upright_and_height(self._torso)[0] >= 0:
        return
      self._flatten(robot, clock)
      if upright_and_height(self._torso)[0] >= 0:
        return
      self._poses(robot, clock, self._roll_poses())

  def _tuck(self, robot, clock) -> None:
    self._flatten(robot, clock)
    self._poses(robot, clock, self._tuck_poses())

  def _stand_up(self, robot, clock) -> None:
    self._poses(robot, clock, self._stand_poses())

  def _poses(self, robot, clock, poses: list[tuple[dict, float]]) -> None:
    for groups, seconds in poses:
      self._pose(robot, clock, groups, seconds)
