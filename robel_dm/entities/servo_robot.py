"""The robot of position-controlled Dynamixel servos that D'Claw and D'Kitty
are.

A `ServoRobot` owns its model, its joints and position actuators (one per
joint, in action order), ROBEL's action map with its velocity clamp, and
its speed and safety limits. A robot is data: a subclass names its model,
joints, speed and safety limits, and finds any extra elements it offers.
"""

import pathlib

from dm_control import composer, mjcf
from dm_control.composer.observation import observable
import numpy as np

from robel_dm import assets
from robel_dm.entities import limits


def load_model(path: pathlib.Path, name: str) -> mjcf.RootElement:
  """Loads an MJCF model and names it (the name prefixes its elements)."""
  root = mjcf.from_path(str(path))
  root.model = name
  return root


def find_all(root: mjcf.RootElement, kind: str, names) -> tuple:
  """The named elements of one kind, in order.

  Raises:
    ValueError: naming the elements the model lacks.
  """
  elements = tuple(root.find(kind, name) for name in names)
  missing = [n for n, e in zip(names, elements, strict=True) if e is None]
  if missing:
    raise ValueError(f'model {root.model!r} has no {kind} {missing}')
  return elements


def address_index(addresses) -> slice | np.ndarray:
  """Indices into MjData arrays: a slice if the addresses are contiguous and
  increasing (cheaper reads and writes), else an index array."""
  addresses = np.asarray(addresses, dtype=int).ravel()
  if addresses.size and np.array_equal(
    addresses, np.arange(addresses[0], addresses[0] + addresses.size)
  ):
    return slice(int(addresses[0]), int(addresses[-1]) + 1)
  return addresses


# The safe action map's targets stay this far inside the position counter's
# bounds, rad (a servo overshoots its target a little), and move at this
# share of the velocity counter's limit.
SAFE_POSITION_BUFFER = np.deg2rad(1.0)
SAFE_SPEED_FRACTION = 0.9


class ActionMap:
  """ROBEL's action map on a compiled model.

  A normalized action a in [-1, 1] per joint becomes the joint target
  center + a * half_range of the actuator's control range, then moves at
  most `max_joint_speed * control_timestep` away from the joint's current
  angle (ROBEL's velocity clamp). `apply` writes the targets into
  `data.ctrl` without allocating.

  The safe map (`safe=True`) narrows both to the robot's safety counters:
  [-1, 1] spans the control range within the position counter's bounds
  (less SAFE_POSITION_BUFFER), and the clamp's speed is SAFE_SPEED_FRACTION
  of the velocity counter's limit. `low` and `high` stay ROBEL's control
  range (observation noise and random poses are drawn on it).
  """

  def __init__(
    self,
    physics: mjcf.Physics,
    robot: 'ServoRobot',
    control_timestep: float,
    *,
    safe: bool = False,
  ):
    ctrl_range = physics.bind(robot.actuators).ctrlrange
    self.low = ctrl_range[:, 0].copy()
    self.high = ctrl_range[:, 1].copy()
    target_low, target_high = self.low, self.high
    speed = robot.max_joint_speed
    if safe:
      target_low, target_high = _safe_target_range(physics, robot)
      speed = min(speed, SAFE_SPEED_FRACTION * robot.safety_limits.max_speed)
    self.center = (target_low + target_high) / 2
    self.half_range = (target_high - target_low) / 2
    self.max_step = speed * control_timestep
    self._qpos_index = address_index(physics.bind(robot.joints).qposadr)
    self._ctrl_index = address_index(physics.bind(robot.actuators).element_id)
    # Views of MjData, read and written in place.
    self._qpos = physics.data.qpos
    self._ctrl = physics.data.ctrl
    self._target = np.zeros(len(robot.actuators))
    self._delta = np.zeros(len(robot.actuators))

  def apply(self, action: np.ndarray) -> None:
    """Writes the joint targets of a (validated) normalized action."""
    target, delta = self._target, self._delta
    np.multiply(action, self.half_range, out=target)
    target += self.center
    qpos = self._qpos[self._qpos_index]
    np.subtract(target, qpos, out=delta)
    np.minimum(delta, self.max_step, out=delta)
    np.maximum(delta, -self.max_step, out=delta)
    np.add(qpos, delta, out=target)
    self._ctrl[self._ctrl_index] = target

  def normalize(self, targets: np.ndarray) -> np.ndarray:
    """Maps joint angles (rad) to actions in [-1, 1]; inverse of the map."""
    action = (np.asarray(targets) - self.center) / self.half_range
    return np.clip(action, -1.0, 1.0)


def _safe_target_range(
  physics: mjcf.Physics, robot: 'ServoRobot'
) -> tuple[np.ndarray, np.ndarray]:
  """The targets of the safe action map: the control range within the
  position counter's bounds, less SAFE_POSITION_BUFFER, rad.

  Raises:
    ValueError: naming a joint whose control range has no such targets.
  """
  ctrl_range = physics.bind(robot.actuators).ctrlrange
  safe_low, safe_high = robot.safe_bounds(physics)
  low = np.maximum(ctrl_range[:, 0], safe_low + SAFE_POSITION_BUFFER)
  high = np.minimum(ctrl_range[:, 1], safe_high - SAFE_POSITION_BUFFER)
  empty = np.flatnonzero(low >= high)
  if empty.size:
    names = [robot.joints[i].name for i in empty]
    raise ValueError(f'no safe targets for joints {names}')
  return low, high


class ServoRobot(composer.Robot):
  """A robot of position-servoed joints; subclasses provide the data.

  Class attributes a subclass sets:
    MODEL: the model file's path parts under `xml/`, e.g. ('dclaw',
      'dclaw.xml').
    DEFAULT_NAME: the model's name (it prefixes element names).
    JOINT_NAMES: the actuated joints in action order; each has a position
      actuator of the same name.
    MAX_JOINT_SPEED: ROBEL's per-joint speed of the action clamp, rad/s.
    SAFETY_LIMITS: thresholds of the safety counters.
  """

  MODEL: tuple[str, ...] = ()
  DEFAULT_NAME: str = ''
  JOINT_NAMES: tuple[str, ...] = ()
  MAX_JOINT_SPEED: float = 0.0
  SAFETY_LIMITS: limits.SafetyLimits | None = None

  def _build(self, name: str | None = None) -> None:
    """Loads the model.

    Args:
      name: model name; it prefixes element names and observable keys.
    """
    root = load_model(assets.xml_path(*self.MODEL), name or self.DEFAULT_NAME)
    self._mjcf_root = root
    self._joints = find_all(root, 'joint', self.JOINT_NAMES)
    self._actuators = find_all(root, 'actuator', self.JOINT_NAMES)
    self._find_parts(root)

  def _find_parts(self, root: mjcf.RootElement) -> None:
    """Finds the robot's other elements (sites, bodies) in its model."""
    del root

  def _build_observables(self) -> 'JointObservables':
    return JointObservables(self)

  @property
  def mjcf_model(self) -> mjcf.RootElement:
    return self._mjcf_root

  @property
  def joints(self) -> tuple[mjcf.Element, ...]:
    """The actuated joints, in action order."""
    return self._joints

  @property
  def actuators(self) -> tuple[mjcf.Element, ...]:
    """The position actuators, in action order."""
    return self._actuators

  @property
  def max_joint_speed(self) -> float:
    return self.MAX_JOINT_SPEED

  @property
  def safety_limits(self) -> limits.SafetyLimits:
    return self.SAFETY_LIMITS

  def action_map(
    self, physics: mjcf.Physics, control_timestep: float, *, safe: bool = False
  ) -> ActionMap:
    """ROBEL's action map (or the safe one) bound to a compiled model."""
    return ActionMap(physics, self, control_timestep, safe=safe)

  def safe_bounds(self, physics: mjcf.Physics) -> tuple[np.ndarray, ...]:
    """Joint angles beyond which the position safety counter counts a
    joint: the limits' range (action or mechanical) less the margin, rad."""
    limits_ = self.SAFETY_LIMITS
    if limits_.position_range == 'joint':
      position_range = physics.bind(self._joints).range
    else:
      position_range = physics.bind(self._actuators).ctrlrange
    low, high = position_range[:, 0].copy(), position_range[:, 1].copy()
    return low + limits_.position_margin, high - limits_.position_margin


class JointObservables(composer.Observables):
  """Joint angles and velocities of a robot with a `joints` property."""

  @composer.observable
  def joints_pos(self):
    return observable.MJCFFeature('qpos', self._entity.joints)

  @composer.observable
  def joints_vel(self):
    return observable.MJCFFeature('qvel', self._entity.joints)
