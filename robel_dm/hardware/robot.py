"""A robot's motors in joint space: calibrated state, limited goals, health.

A robot belongs to the process that opened it: a forked child (os.fork,
multiprocessing's fork start method) inherits it, and every command it
gives, a release included, raises `RobotOwnerError` before anything is
sent. The robot also remembers which motors it turned on, and every read
checks that they still hold their torque: one released by anyone else
(another program on the bus, a motor that lost power) stops the next
control step instead of being driven on limp.
"""

import logging
import os
import time

import numpy as np

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table

# One sync read covers input voltage and temperature (addresses 144..146);
# it reads 4 bytes because dynamixel_sdk decodes only 1, 2 or 4.
_HEALTH_BLOCK = table.Item(table.PRESENT_INPUT_VOLTAGE.address, 4)


class RobotOwnerError(dynamixel.DynamixelError):
  """A process other than the robot's owner (a forked child) used it."""


# Unless the robot's configuration sets others (`RobotConfig.health`).
_DEFAULT_HEALTH = config_lib.HealthLimits()


class HardwareRobot:
  """The motors that drive a model's joints, in joint units.

  `joints` are the actuated joints in action order, `auxiliary` any other
  motors the task reads (e.g. the D'Claw's valve encoder); `positions` and
  its siblings hold the joints, then the auxiliary motors. Reads convert
  motor angles to joint angles with each motor's calibration; goals are
  clamped to the joints' limits before they are converted and sent.
  """

  def __init__(
    self,
    client: dynamixel.DynamixelClient,
    joints: tuple[config_lib.Motor, ...],
    auxiliary: tuple[config_lib.Motor, ...] = (),
    health: config_lib.HealthLimits = _DEFAULT_HEALTH,
  ):
    self._client = client
    self._joints = joints
    self._auxiliary = auxiliary
    motors = joints + auxiliary
    index = {motor_id: i for i, motor_id in enumerate(client.motor_ids)}
    missing = [m.id for m in motors if m.id not in index]
    if missing:
      raise ValueError(f'motors {missing} are not on the client')
    self._columns = np.array([index[m.id] for m in motors])
    self._scale = np.array([m.scale for m in motors])
    self._offset = np.array([m.offset for m in motors])
    self._joint_ids = tuple(m.id for m in joints)
    self._limits = (np.full(len(joints), -np.inf), np.full(len(joints), np.inf))
    # The configuration's own limits: resets go beyond the action ranges,
    # never beyond these.
    self._configured: dict[str, tuple[float, float]] = {}
    self._health = health
    self._steps_since_check = 0
    self._owner = os.getpid()
    # Motors this robot turned on and has not turned off since (motor_ids
    # order): each read checks that they still hold their torque.
    self._torqued = np.zeros(len(motors), dtype=bool)
    self.positions = np.zeros(len(motors))  # Joint angles, rad.
    self.velocities = np.zeros(len(motors))  # rad/s.
    self.currents = np.zeros(len(motors))  # mA.
    # Health, read every `check_every` steps (see `check_health`).
    self.temperatures = np.zeros(len(motors))  # C.
    self.voltages = np.zeros(len(motors))  # Input voltage, V.
    self.hardware_errors = np.zeros(len(motors), dtype=np.int64)  # Bits.
    self.health_time = float('nan')  # Clock (time.monotonic) of that read.

  @property
  def client(self) -> dynamixel.DynamixelClient:
    return self._client

  @property
  def in_owner_process(self) -> bool:
    """Whether this process opened the robot (False in a forked child)."""
    return os.getpid() == self._owner

  def _check_owner(self) -> None:
    if not self.in_owner_process:
      raise RobotOwnerError(
        f'this robot belongs to process {self._owner}, which opened it; '
        f'process {os.getpid()} (forked from it) may neither drive nor '
        'release it: open the robot in the process that drives it'
      )

  @property
  def joint_ids(self) -> tuple[int, ...]:
    return self._joint_ids

  @property
  def motor_ids(self) -> tuple[int, ...]:
    """IDs in the order of `positions`: joints, then auxiliary motors."""
    return self._joint_ids + tuple(m.id for m in self._auxiliary)

  @property
  def auxiliary(self) -> tuple[config_lib.Motor, ...]:
    return self._auxiliary

  def set_joint_limits(self, low, high, configured=None) -> None:
    """Goal limits of the actuated joints, rad.

    Args:
      low: lower limits (the model's action range).
      high: upper limits.
      configured: joint name -> (low, high) from the robot configuration;
        they narrow the limits further.
    """
    low_range, high_range = np.array(low, float), np.array(high, float)
    low, high = low_range.copy(), high_range.copy()
    self._configured = dict(configured or {})
    for i, motor in enumerate(self._joints):
      if configured and motor.name in configured:
        low[i] = max(low[i], configured[motor.name][0])
        high[i] = min(high[i], configured[motor.name][1])
    for i in np.flatnonzero(low > high):
      name = self._joints[i].name
      raise config_lib.ConfigError(
        f'configured limits of {name} {list(configured[name])} lie outside '
        f'its action range [{low_range[i]:+.3f}, {high_range[i]:+.3f}] rad'
      )
    self._limits = (low, high)

  def read(self) -> None:
    """Reads every motor into `positions`, `velocities`, `currents`, and
    checks that the motors this robot turned on still hold their torque.

    Raises:
      dynamixel.DynamixelError: on communication failure.
      dynamixel.MotorFaultError: on over-current, or a motor that cut its
        torque on a hardware error.
      dynamixel.RobotReleasedError: naming the motors that lost their
        torque otherwise.
      RobotOwnerError: in a process that did not open the robot.
    """
    self._check_owner()
    state = self._client.read_state()[:, self._columns]
    np.multiply(state[2], self._scale, out=self.positions)
    self.positions += self._offset
    np.multiply(state[1], self._scale, out=self.velocities)
    # Current is not calibrated (ROBEL leaves its sign as the motor's).
    self.currents[:] = state[0]
    over = np.flatnonzero(np.abs(self.currents) > self._health.max_current)
    if over.size:
      ids = [self.motor_ids[i] for i in over]
      raise dynamixel.MotorFaultError(
        f'over-current on motors {ids}: '
        f'{self.currents[over].round().tolist()} mA '
        f'(limit {self._health.max_current} mA)',
        {motor_id: 0 for motor_id in ids},
      )
    if self._torqued.any():
      self._check_torque()

  def _check_torque(self) -> None:
    """Raises if a motor this robot turned on has its torque off.

    One sync read of Torque Enable, one byte per motor: about 1.3 ms of
    wire time for 9 motors at 1 Mbps, on top of the Return Delay Time.
    """
    held = self._client.sync_read_register(table.TORQUE_ENABLE)
    ids = self.motor_ids
    lost = [ids[i] for i in np.flatnonzero(self._torqued) if not held[ids[i]]]
    if not lost:
      return
    # An overload (or other shutdown) error cuts a motor's torque: name it.
    self._raise_on_hardware_errors(lost)
    raise dynamixel.RobotReleasedError(
      f'motors {lost} lost their torque: released by another process or '
      'program on the bus, or their power failed; the robot is released, '
      'and reset() brings it back',
      lost,
    )

  def _raise_on_hardware_errors(self, motor_ids=None) -> None:
    """Raises MotorFaultError if any of `motor_ids` (all by default) reports
    a hardware error, its bits kept in `hardware_errors`."""
    try:
      self._client.raise_on_hardware_errors(motor_ids)
    except dynamixel.MotorFaultError as fault:
      self.hardware_errors[:] = [fault.errors.get(i, 0) for i in self.motor_ids]
      raise

  def _mark_torque(self, motor_ids, enabled: bool) -> None:
    index = {motor_id: i for i, motor_id in enumerate(self.motor_ids)}
    self._torqued[[index[i] for i in motor_ids if i in index]] = enabled

  def write_joint_goals(self, targets) -> np.ndarray:
    """Sends goals for the actuated joints, clamped to their limits.

    Returns:
      The goals sent, rad.

    Raises:
      ValueError: for non-finite targets (nothing is sent).
      RobotOwnerError: in a process that did not open the robot.
    """
    self._check_owner()
    targets = np.asarray(targets, dtype=float)
    if not np.all(np.isfinite(targets)):
      raise ValueError(f'non-finite joint goals {targets.tolist()}')
    goals = np.clip(targets, *self._limits)
    n = len(self._joints)
    motor_angles = (goals - self._offset[:n]) / self._scale[:n]
    self._client.write_goal_positions(motor_angles, self._joint_ids)
    return goals

  def reset_goals(self, pose) -> np.ndarray:
    """The episode's initial joint angles within the goal limits, rad.

    A task draws its initial pose within the action ranges; a configuration's
    narrower `limits` can exclude it. Such joints start the episode at their
    limit, and a warning names each before anything moves (the observation
    reads where the robot is).
    """
    pose = np.asarray(pose, dtype=float)
    goals = np.clip(pose, *self._limits)
    for i in np.flatnonzero(goals != pose):
      logging.warning(
        'reset: joint %s starts at %+.3f rad, the limit of its goals, not at '
        'the %+.3f rad the task drew',
        self._joints[i].name,
        goals[i],
        pose[i],
      )
    return goals

  def check_configured_limits(self, motor_ids, joint_angles) -> None:
    """Raises ValueError naming the first of the joints `motor_ids` whose
    angle lies outside the limits its robot configuration sets (`limits`;
    joints without them take any finite angle)."""
    for motor_id, angle in zip(motor_ids, joint_angles, strict=True):
      name = self._joints[self._joint_ids.index(motor_id)].name
      low, high = self._configured.get(name, (-np.inf, np.inf))
      if not low <= angle <= high:
        raise ValueError(
          f'joint {name} (motor {motor_id}) would go to {angle:+.3f} rad, '
          f'outside its configured limits [{low:+.3f}, {high:+.3f}]'
        )

  def write_reset_goals(self, motor_ids, joint_angles) -> None:
    """Goals for some joints beyond the action ranges (resets), within the
    configuration's limits.

    Raises:
      ValueError: for non-finite angles, unknown motors or angles outside
        the configured limits (nothing is sent).
      RobotOwnerError: in a process that did not open the robot.
    """
    self._check_owner()
    joint_angles = np.asarray(joint_angles, dtype=float)
    if not np.all(np.isfinite(joint_angles)):
      raise ValueError(f'non-finite joint goals {joint_angles.tolist()}')
    self.check_configured_limits(motor_ids, joint_angles)
    motors = [self._joints[self._joint_ids.index(i)] for i in motor_ids]
    self._client.write_goal_positions(
      [m.to_motor(a) for m, a in zip(motors, joint_angles, strict=True)],
      motor_ids,
    )

  def positions_of(self, motor_ids) -> np.ndarray:
    """Last read joint angles of some joints, rad."""
    return self.positions[[self._joint_ids.index(i) for i in motor_ids]]

  def write_auxiliary_goal(self, name: str, joint_angle: float) -> None:
    """Sends a goal to an auxiliary motor (e.g. the valve during a reset)."""
    self._check_owner()
    motor = self._find_auxiliary(name)
    self._client.write_goal_positions([motor.to_motor(joint_angle)], [motor.id])

  def auxiliary_id(self, name: str) -> int:
    return self._find_auxiliary(name).id

  def auxiliary_index(self, name: str) -> int:
    """Index of an auxiliary motor in `positions` and friends."""
    motor = self._find_auxiliary(name)
    return len(self._joints) + self._auxiliary.index(motor)

  def _find_auxiliary(self, name: str) -> config_lib.Motor:
    for motor in self._auxiliary:
      if motor.name == name:
        return motor
    raise KeyError(f'no auxiliary motor {name!r}')

  def set_torque(self, enabled: bool, motor_ids=None) -> None:
    """Turns the torque of some motors (all by default) on or off.

    Raises:
      dynamixel.DynamixelError: naming motors that refuse.
      RobotOwnerError: in a process that did not open the robot.
    """
    self._check_owner()
    ids = self._client.motor_ids if motor_ids is None else tuple(motor_ids)
    if not enabled:
      self._mark_torque(ids, False)  # Off, or unknown: no longer checked.
    self._client.set_torque(ids, enabled)
    if enabled:
      self._mark_torque(ids, True)

  def check_health(self, force: bool = False) -> None:
    """Every `check_every` calls (or now), reads the hardware-error bits,
    input voltage and temperature into `hardware_errors`, `voltages` and
    `temperatures`. Error bits stop the robot, so `hardware_errors` is 0
    after every check that returns, and holds the bits after one that
    raised.

    Raises:
      dynamixel.MotorFaultError: on a hardware error or over-temperature.
      RobotOwnerError: in a process that did not open the robot.
    """
    self._check_owner()
    self._steps_since_check += 1
    if not force and self._steps_since_check < self._health.check_every:
      return
    self._steps_since_check = 0
    # A motor with an error stops the robot here; otherwise every bit is 0.
    self._raise_on_hardware_errors()
    self.hardware_errors[:] = 0
    block = self._client.sync_read_register(_HEALTH_BLOCK)
    ids = self.motor_ids
    values = np.array([block[i] for i in ids], dtype=np.int64)
    self.voltages[:] = (values & 0xFFFF) * table.VOLTS_PER_UNIT
    self.temperatures[:] = (values >> 16) & 0xFF
    self.health_time = time.monotonic()
    temperatures = dict(zip(ids, self.temperatures.tolist(), strict=True))
    hot = {
      i: t for i, t in temperatures.items() if t > self._health.max_temperature
    }
    if hot:
      raise dynamixel.MotorFaultError(
        f'over-temperature (C) {hot}, limit {self._health.max_temperature}',
        hot,
      )

  def release(self) -> None:
    """Turns every motor's torque off; logs instead of raising, and no
    signal interrupts it (see `DynamixelClient.release`).

    Raises:
      RobotOwnerError: in a process that did not open the robot (its
        owner releases it).
    """
    self._check_owner()
    self._torqued[:] = False
    self._client.release()
