"""Calibrated joint dynamics: what system identification fits and the
simulation applies.

A calibration file (JSON) holds, per joint of one robot, the simulation
parameters that matter most for sim-to-real transfer, in SI units, and one
control delay for the whole robot:

    {
      "format": "robel_dm-calibration", "version": 1,
      "domain": "dclaw",
      "control_delay": 0.0075,
      "joints": {
        "FFJ10": {"kp": 2.3, "damping": 0.12, "frictionloss": 0.02,
                  "armature": 0.0011},
        ...
      },
      "fit": {...}
    }

  kp: the position servo's gain, N m/rad (MuJoCo `<position kp>`).
  damping: joint damping, N m s/rad.
  frictionloss: joint dry friction, N m.
  armature: the motor's reflected inertia added to the joint, kg m^2.
  max_torque: the most torque the servo gives, N m (a weaker or hot motor
    gives less); unlimited when absent.
  control_delay: seconds between a goal being sent and the servo acting on
    it (simulated in whole physics steps, below one control step).
  sensor_noise: standard deviation of the noise on each position a servo
    reports, rad (optional; only a virtual bus applies it, before rounding to
    the servo's ticks).
  fit: how the values were fitted (optional, informative only).

A joint may give any subset of the four parameters, and joints not listed
keep the model's values. `robel-sysid fit` writes these files;
`suite.load(..., dynamics=FILE)` applies one (see docs/sysid.md).
"""

import dataclasses
import json
import math
import os
import pathlib
from typing import Any

from dm_control import mjcf

from robel_dm import numeric

FORMAT = 'robel_dm-calibration'
VERSION = 1
# The fitted joint parameters, in file order.
PARAMETERS = ('kp', 'damping', 'frictionloss', 'armature')
# Every joint parameter a file may give: the fitted ones and those a person
# sets (a weaker motor for a held-out test robot).
JOINT_PARAMETERS = (*PARAMETERS, 'max_torque')
# The MJCF element and attribute each parameter sets.
_MJCF_ATTRIBUTE = {
  'kp': ('actuator', 'kp'),
  'damping': ('joint', 'damping'),
  'frictionloss': ('joint', 'frictionloss'),
  'armature': ('joint', 'armature'),
  'max_torque': ('actuator', 'forcerange'),
}


# Parameters that must be above zero (the others may be zero).
_POSITIVE = ('kp', 'max_torque')


class CalibrationError(ValueError):
  """A calibration file is malformed or does not fit the robot (named)."""


@dataclasses.dataclass(frozen=True)
class Calibration:
  """Joint dynamics of one robot.

  Attributes:
    domain: the robot, 'dclaw' or 'dkitty'.
    joints: joint name -> {parameter name -> value} (see
      `JOINT_PARAMETERS`).
    control_delay: goal-to-servo delay, s.
    fit: how it was fitted (free-form; not applied).
    sensor_noise: standard deviation of reported positions' noise, rad.
    source: where it was read from (for messages).
  """

  domain: str
  joints: dict[str, dict[str, float]]
  control_delay: float = 0.0
  fit: dict[str, Any] = dataclasses.field(default_factory=dict)
  source: str = '<memory>'
  sensor_noise: float = 0.0

  def to_dict(self) -> dict[str, Any]:
    return {
      'format': FORMAT,
      'version': VERSION,
      'domain': self.domain,
      'control_delay': self.control_delay,
      'sensor_noise': self.sensor_noise,
      'joints': self.joints,
      'fit': self.fit,
    }


def _number(value, where: str, minimum: float, strict: bool) -> float:
  if not numeric.is_real(value):
    raise CalibrationError(f'{where} must be a number, got {value!r}')
  value = float(value)
  if not math.isfinite(value) or value < minimum or (strict and value == 0):
    bound = f'> {minimum}' if strict else f'>= {minimum}'
    raise CalibrationError(f'{where} must be finite and {bound}, got {value}')
  return value


def from_dict(data: Any, source: str = '<memory>') -> Calibration:
  """Validates a calibration's JSON object.

  Raises:
    CalibrationError: naming the source and the offending entry.
  """
  if not isinstance(data, dict):
    raise CalibrationError(f'{source}: a calibration is a JSON object')
  if data.get('format') != FORMAT:
    raise CalibrationError(
      f'{source}: not a robel_dm calibration (format must be {FORMAT!r})'
    )
  if data.get('version') != VERSION:
    raise CalibrationError(
      f'{source}: calibration version {data.get("version")!r}; this robel_dm '
      f'reads version {VERSION}'
    )
  domain = data.get('domain')
  if not isinstance(domain, str):
    raise CalibrationError(f'{source}: "domain" must name the robot')
  joints = data.get('joints')
  if not isinstance(joints, dict) or not joints:
    raise CalibrationError(f'{source}: "joints" must map joint names to values')
  parsed = {}
  for name, values in joints.items():
    where = f'{source}: joints.{name}'
    if not isinstance(values, dict):
      raise CalibrationError(f'{where} must be an object')
    unknown = sorted(set(values) - set(JOINT_PARAMETERS))
    if unknown:
      raise CalibrationError(
        f'{where}: unknown parameters {unknown}; expected some of '
        f'{list(JOINT_PARAMETERS)}'
      )
    parsed[name] = {
      key: _number(values[key], f'{where}.{key}', 0.0, strict=key in _POSITIVE)
      for key in JOINT_PARAMETERS
      if key in values
    }
  delay = _number(
    data.get('control_delay', 0.0), f'{source}: control_delay', 0.0, False
  )
  noise = _number(
    data.get('sensor_noise', 0.0), f'{source}: sensor_noise', 0.0, False
  )
  fit = data.get('fit', {})
  if not isinstance(fit, dict):
    raise CalibrationError(f'{source}: "fit" must be an object')
  return Calibration(domain, parsed, delay, fit, source, noise)


def load(path: str | os.PathLike) -> Calibration:
  """Reads a calibration file.

  Raises:
    CalibrationError: if it is missing, not JSON, or malformed.
  """
  path = pathlib.Path(path)
  try:
    data = json.loads(path.read_text())
  except FileNotFoundError as error:
    raise CalibrationError(f'no calibration file {path}') from error
  except (OSError, ValueError) as error:
    raise CalibrationError(
      f'cannot read calibration {path}: {error}'
    ) from error
  return from_dict(data, source=str(path))


def save(calibration: Calibration, path: str | os.PathLike) -> None:
  """Writes a calibration file (atomically)."""
  path = pathlib.Path(path)
  partial = path.with_name(path.name + '.partial')
  partial.write_text(json.dumps(calibration.to_dict(), indent=1) + '\n')
  os.replace(partial, path)


def resolve(dynamics) -> Calibration:
  """A `Calibration`, or one read from a path."""
  if isinstance(dynamics, Calibration):
    return dynamics
  if isinstance(dynamics, str | os.PathLike):
    return load(dynamics)
  raise CalibrationError(
    f'dynamics must be a calibration file path or a Calibration, got '
    f'{type(dynamics).__name__}'
  )


def apply_to_model(
  calibration: Calibration,
  domain: str,
  joints: tuple[mjcf.Element, ...],
  actuators: tuple[mjcf.Element, ...],
) -> None:
  """Writes the calibrated values into a robot's MJCF (before compiling).

  Args:
    calibration: the values.
    domain: the robot's domain; must be the calibration's.
    joints: the robot's actuated joints, in action order.
    actuators: their position actuators, in the same order.

  Raises:
    CalibrationError: for another robot's calibration or unknown joints.
  """
  if calibration.domain != domain:
    raise CalibrationError(
      f'{calibration.source} calibrates a {calibration.domain}, not a {domain}'
    )
  elements = {
    joint.name: {'joint': joint, 'actuator': actuator}
    for joint, actuator in zip(joints, actuators, strict=True)
  }
  unknown = sorted(set(calibration.joints) - set(elements))
  if unknown:
    raise CalibrationError(
      f'{calibration.source}: joints {unknown} are not {domain} joints '
      f'{list(elements)}'
    )
  for name, values in calibration.joints.items():
    for parameter, value in values.items():
      kind, attribute = _MJCF_ATTRIBUTE[parameter]
      element = elements[name][kind]
      if parameter == 'max_torque':
        element.forcelimited = True
        value = (-value, value)
      setattr(element, attribute, value)
