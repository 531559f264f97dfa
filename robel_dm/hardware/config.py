"""Robot configurations: which motor drives which joint, and how.

A configuration is data (JSON), so that a robot with other wiring or other
calibration offsets needs a new file, not new code. The shipped defaults are
ROBEL's (docs/robel_reference.md section 4.1): `configs/dclaw.json` and
`configs/dkitty.json`.

Calibration maps a motor's own angle (ticks * 2 pi / 4096, rad) to the
joint angle of the model: q = scale * motor_angle + offset; velocities are
scaled likewise without the offset.

File format (JSON object; unknown fields are refused):
  robot: 'dclaw' or 'dkitty'.
  description (optional): text for people.
  baud_rate: bits per second (default 1000000).
  joints: the actuated joints in action order, each
      {"name": str, "id": int, "scale": +1 or -1,
       "offset": rad or "offset_pi": multiple of pi}.
  auxiliary: other motors, e.g. the D'Claw's valve encoder, same fields plus
      "optional": bool and "required_by": [task family, ...].
  groups: name -> list of motor IDs (for resets and torque control).
  limits (optional): joint name -> [low, high] goal limits, rad; by default
      the model's action range.
  health (optional): {"max_current": mA, "max_temperature": C}, the limits
      above which a motor's current or temperature stops the episode and
      releases the robot; by default 1500 mA and 70 C.
"""

import dataclasses
import importlib.resources
import json
import math
import os
import pathlib
from typing import Any

from robel_dm import numeric, robots
from robel_dm.hardware.dynamixel import control_table

_MAX_ID = 252


class ConfigError(ValueError):
  """A robot configuration is malformed; the message says where."""


@dataclasses.dataclass(frozen=True)
class Motor:
  """One motor and its calibration.

  Attributes:
    name: joint name in the model (or an auxiliary role such as 'valve').
    id: Dynamixel ID.
    scale: +1 or -1: how the motor's angle maps to the joint's.
    offset: joint angle at motor angle 0, rad.
    optional: whether the robot may lack this motor.
    required_by: task families that need it (auxiliary motors).
  """

  name: str
  id: int
  scale: float
  offset: float
  optional: bool = False
  required_by: tuple[str, ...] = ()

  def to_joint(self, motor_angle):
    return self.scale * motor_angle + self.offset

  def to_motor(self, joint_angle):
    return (joint_angle - self.offset) / self.scale


@dataclasses.dataclass(frozen=True)
class HealthLimits:
  """Limits that stop an episode and release the motors.

  Attributes:
    max_current: |current| above this on any motor is a fault, mA.
    max_temperature: temperature above this on any motor is a fault, C.
    check_every: control steps between reads of the hardware-error and
      temperature registers (one read per motor each).
  """

  max_current: float = 1500.0
  max_temperature: float = 70.0
  check_every: int = 10


# The health limits a configuration file may set.
_HEALTH_FIELDS = ('max_current', 'max_temperature')
# The fields of a configuration file and of each motor in it.
_FIELDS = (
  'robot', 'description', 'baud_rate', 'joints', 'auxiliary', 'groups',
  'limits', 'health',
)  # fmt: skip
_MOTOR_FIELDS = (
  'name', 'id', 'scale', 'offset', 'offset_pi', 'optional', 'required_by'
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class RobotConfig:
  """The motors of one robot and how they map to the model's joints."""

  robot: str
  joints: tuple[Motor, ...]
  auxiliary: tuple[Motor, ...] = ()
  groups: dict[str, tuple[int, ...]] = dataclasses.field(default_factory=dict)
  limits: dict[str, tuple[float, float]] = dataclasses.field(
    default_factory=dict
  )
  baud_rate: int = control_table.DEFAULT_BAUD_RATE
  health: HealthLimits = HealthLimits()
  source: str = '<memory>'

  @property
  def joint_ids(self) -> tuple[int, ...]:
    return tuple(motor.id for motor in self.joints)

  def describe(self) -> dict[str, Any]:
    """The configuration as JSON-ready data (for recordings)."""
    data = dataclasses.asdict(self)
    data['groups'] = {k: list(v) for k, v in self.groups.items()}
    return data

  def auxiliary_motor(self, name: str) -> Motor | None:
    for motor in self.auxiliary:
      if motor.name == name:
        return motor
    return None

  def group(self, name: str) -> tuple[int, ...]:
    try:
      return self.groups[name]
    except KeyError:
      raise ConfigError(
        f'{self.source}: no motor group {name!r}; groups: {sorted(self.groups)}'
      ) from None


def _require(data: dict, key: str, where: str):
  if key not in data:
    raise ConfigError(f'{where}: missing "{key}"')
  return data[key]


def _unknown(data: dict, known: tuple[str, ...], where: str) -> None:
  unknown = sorted(set(data) - set(known))
  if unknown:
    raise ConfigError(
      f'{where}: unknown fields {unknown}; known: {list(known)}'
    )


def _motor(data: Any, where: str) -> Motor:
  if not isinstance(data, dict):
    raise ConfigError(f'{where}: expected an object, got {data!r}')
  name = _require(data, 'name', where)
  if not isinstance(name, str):
    raise ConfigError(f'{where}: name must be a string, got {name!r}')
  where = f'{where} ({name})'
  _unknown(data, _MOTOR_FIELDS, where)
  motor_id = _require(data, 'id', where)
  if not numeric.is_integer(motor_id) or not 0 <= motor_id <= _MAX_ID:
    raise ConfigError(
      f'{where}: id must be an integer 0..252, got {motor_id!r}'
    )
  scale = data.get('scale', 1)
  if not numeric.is_finite(scale) or scale not in (1, -1):
    raise ConfigError(f'{where}: scale must be 1 or -1, got {scale!r}')
  if 'offset' in data and 'offset_pi' in data:
    raise ConfigError(f'{where}: give "offset" or "offset_pi"')
  offset = data.get('offset', data.get('offset_pi', 0.0))
  if not numeric.is_finite(offset):
    raise ConfigError(
      f'{where}: offset must be a finite number, got {offset!r}'
    )
  if 'offset_pi' in data:
    offset = math.pi * offset
  optional = data.get('optional', False)
  if not isinstance(optional, bool):
    raise ConfigError(
      f'{where}: optional must be true or false, got {optional!r}'
    )
  required_by = data.get('required_by', [])
  if not isinstance(required_by, list) or not all(
    isinstance(family, str) for family in required_by
  ):
    raise ConfigError(
      f'{where}: required_by must be a list of task families, got '
      f'{required_by!r}'
    )
  return Motor(
    name=name,
    id=motor_id,
    scale=float(scale),
    offset=float(offset),
    optional=optional,
    required_by=tuple(required_by),
  )


def from_dict(data: dict, source: str = '<memory>') -> RobotConfig:
  """Validates and builds a configuration.

  Raises:
    ConfigError: naming the file and the offending entry.
  """
  if not isinstance(data, dict):
    raise ConfigError(f'{source}: a configuration is a JSON object')
  _unknown(data, _FIELDS, source)
  robot = _require(data, 'robot', source)
  if robot not in robots.ROBOTS:
    raise ConfigError(
      f'{source}: robot must be one of {sorted(robots.ROBOTS)}, got {robot!r}'
    )
  joints = tuple(
    _motor(entry, f'{source}: joints[{i}]')
    for i, entry in enumerate(_list(data, 'joints', source, required=True))
  )
  auxiliary = tuple(
    _motor(entry, f'{source}: auxiliary[{i}]')
    for i, entry in enumerate(_list(data, 'auxiliary', source))
  )
  ids = [motor.id for motor in joints + auxiliary]
  duplicates = sorted({i for i in ids if ids.count(i) > 1})
  if duplicates:
    raise ConfigError(f'{source}: motor IDs used twice: {duplicates}')
  baud_rate = data.get('baud_rate', control_table.DEFAULT_BAUD_RATE)
  if not numeric.is_integer(baud_rate) or (
    baud_rate not in control_table.BAUD_RATES.values()
  ):
    raise ConfigError(
      f'{source}: baud_rate {baud_rate!r} is not a Dynamixel rate '
      f'{sorted(control_table.BAUD_RATES.values())}'
    )
  return RobotConfig(
    robot=robot,
    joints=joints,
    auxiliary=auxiliary,
    groups=_groups(data.get('groups', {}), ids, source),
    limits=_limits(data.get('limits', {}), joints, source),
    baud_rate=int(baud_rate),
    health=_health(data.get('health', {}), source),
    source=source,
  )


def _list(data: dict, key: str, source: str, required: bool = False) -> list:
  """The list under `key` (empty if absent and not `required`)."""
  value = _require(data, key, source) if required else data.get(key, [])
  if not isinstance(value, list):
    raise ConfigError(f'{source}: {key} must be a list, got {value!r}')
  return value


def _groups(data: Any, ids: list[int], source: str) -> dict:
  """The `groups` entry: name -> motor IDs, each a configured motor."""
  if not isinstance(data, dict):
    raise ConfigError(f'{source}: groups must be an object, got {data!r}')
  groups = {}
  for name, members in data.items():
    if not isinstance(members, list):
      raise ConfigError(
        f'{source}: group {name!r} must be a list of motor IDs, got {members!r}'
      )
    unknown = [i for i in members if not numeric.is_integer(i) or i not in ids]
    if unknown:
      raise ConfigError(f'{source}: group {name!r} has unknown IDs {unknown}')
    groups[name] = tuple(members)
  return groups


def _limits(data: Any, joints: tuple[Motor, ...], source: str) -> dict:
  """The `limits` entry: joint name -> (low, high), rad."""
  if not isinstance(data, dict):
    raise ConfigError(f'{source}: limits must be an object, got {data!r}')
  limits = {}
  joint_names = {motor.name for motor in joints}
  for name, bounds in data.items():
    if name not in joint_names:
      raise ConfigError(f'{source}: limits for unknown joint {name!r}')
    if (
      not isinstance(bounds, list)
      or len(bounds) != 2
      or not all(map(numeric.is_finite, bounds))
      or bounds[0] >= bounds[1]
    ):
      raise ConfigError(
        f'{source}: limits of {name} must be [low, high] in rad, low < '
        f'high, got {bounds!r}'
      )
    limits[name] = (float(bounds[0]), float(bounds[1]))
  return limits


def _health(data: Any, source: str) -> HealthLimits:
  """The `health` entry of a configuration as HealthLimits."""
  if not isinstance(data, dict):
    raise ConfigError(f'{source}: health must be an object {_HEALTH_FIELDS}')
  _unknown(data, _HEALTH_FIELDS, f'{source}: health')
  for name, value in data.items():
    if not numeric.is_finite(value) or value <= 0:
      raise ConfigError(
        f'{source}: health {name} must be a positive number, got {value!r}'
      )
  return HealthLimits(**{name: float(v) for name, v in data.items()})


def load(path: str | os.PathLike) -> RobotConfig:
  """Loads a configuration file.

  Raises:
    ConfigError: if the file is missing, not JSON or malformed.
  """
  path = pathlib.Path(path)
  try:
    data = json.loads(path.read_text())
  except FileNotFoundError:
    raise ConfigError(f'robot configuration not found: {path}') from None
  except json.JSONDecodeError as error:
    raise ConfigError(f'{path}: not valid JSON: {error}') from None
  return from_dict(data, source=str(path))


def default(robot: str) -> RobotConfig:
  """ROBEL's configuration of `robot` ('dclaw' or 'dkitty')."""
  if robot not in robots.ROBOTS:
    raise ConfigError(f'no shipped configuration for robot {robot!r}')
  resource = (
    importlib.resources.files(__package__)
    / 'configs'
    / robots.ROBOTS[robot].config_file
  )
  if not resource.is_file():
    raise ConfigError(f'no shipped configuration for robot {robot!r}')
  return from_dict(json.loads(resource.read_text()), source=f'default {robot}')
