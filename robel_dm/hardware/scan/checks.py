"""What is wrong with a scanned bus, for ROBEL.

`problems` turns the scan's `MotorReport`s into `Problem`s: a bus where no
motor answers, missing or unexpected motors, unknown models, modes other
than position control, return delays that cost bus time, a status return
level below 2, a baud register that differs from the bus, narrowed position
limits and latched hardware errors. ERROR problems decide the command's exit
status; WARNING ones are reported only.
"""

from collections.abc import Iterable, Sequence
import dataclasses

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.scan.probe import MAX_ID, MotorReport

_FULL_POSITION_RANGE = (0, 4_095)

ERROR = 'error'
WARNING = 'warning'

# Problem kinds.
MISSING = 'missing'
NO_MOTORS = 'no_motors'
EXTRA = 'extra'
UNKNOWN_MODEL = 'unknown_model'
UNREADABLE = 'unreadable'
OPERATING_MODE = 'operating_mode'
RETURN_DELAY = 'return_delay'
STATUS_RETURN_LEVEL = 'status_return_level'
BAUD_RATE = 'baud_rate'
POSITION_LIMITS = 'position_limits'
HARDWARE_ERROR = 'hardware_error'


@dataclasses.dataclass(frozen=True)
class Problem:
  """A finding; `message` is a full line naming the motor.

  Attributes:
    kind: one of the kind constants (MISSING, OPERATING_MODE, ...).
    motor_id: the motor concerned (None for the bus as a whole).
    message: what is wrong and what to do.
    severity: ERROR (exit status 1) or WARNING (reported only).
  """

  kind: str
  motor_id: int | None
  message: str
  severity: str = ERROR

  def __str__(self) -> str:
    return f'{self.severity.upper():7} {self.message}'


def configured_motors(
  robot_config: config_lib.RobotConfig | None,
) -> dict[int, config_lib.Motor]:
  """The configuration's motors (joints and auxiliary) by ID; {} for None."""
  if robot_config is None:
    return {}
  return {m.id: m for m in robot_config.joints + robot_config.auxiliary}


def expected_ids(
  robot_config: config_lib.RobotConfig | None, ids: Iterable[int] = ()
) -> list[int]:
  """The motors a scan looks for: the configuration's and `ids`."""
  return sorted(set(configured_motors(robot_config)) | set(ids))


def label(
  motor_id: int, robot_config: config_lib.RobotConfig | None = None
) -> str:
  """'motor 10 (FFJ10)', or 'motor 99' for a motor not in the config."""
  motor = configured_motors(robot_config).get(motor_id)
  return f'motor {motor_id} ({motor.name})' if motor else f'motor {motor_id}'


def format_baud(bits_per_second: int | None) -> str:
  """'1,000,000 bps', or '?' for an unknown rate."""
  if bits_per_second is None:
    return '?'
  return f'{bits_per_second:,} bps'


def _missing_problems(found, robot_config, ids) -> list[Problem]:
  problems_ = []
  motors = configured_motors(robot_config)
  for motor_id in expected_ids(robot_config, ids):
    if motor_id in found:
      continue
    motor = motors.get(motor_id)
    name = label(motor_id, robot_config)
    if motor is None or motor in robot_config.joints:
      problems_.append(
        Problem(MISSING, motor_id, f'{name}: expected but not found')
      )
    elif motor.optional and motor_id not in ids:
      continue
    elif motor.required_by and motor_id not in ids:
      tasks = ', '.join(motor.required_by)
      problems_.append(
        Problem(
          MISSING,
          motor_id,
          f'{name}: not found; the {tasks} tasks need it',
          WARNING,
        )
      )
    else:
      problems_.append(
        Problem(MISSING, motor_id, f'{name}: expected but not found')
      )
  return problems_


def _limit_problem(report, robot_config) -> Problem | None:
  low, high = report.min_position_limit, report.max_position_limit
  if low is None or (low, high) == _FULL_POSITION_RANGE:
    return None
  if low <= _FULL_POSITION_RANGE[0] and high >= _FULL_POSITION_RANGE[1]:
    return None
  name = label(report.id, robot_config)
  message = (
    f'{name}: position limits {low}..{high} narrower than '
    f'{_FULL_POSITION_RANGE[0]}..{_FULL_POSITION_RANGE[1]}; goals outside '
    'them are refused (Data Limit error)'
  )
  motor = configured_motors(robot_config).get(report.id)
  severity = WARNING
  if motor is not None:
    ends = sorted(
      motor.to_joint(t * table.RADIANS_PER_TICK) for t in (low, high)
    )
    message += (
      f': joint {motor.name} kept within [{ends[0]:.3f}, {ends[1]:.3f}] rad'
    )
    needed = robot_config.limits.get(motor.name)
    if needed is not None:
      if ends[0] <= needed[0] and ends[1] >= needed[1]:
        message += f', which covers its configured limits {list(needed)}'
      else:
        severity = ERROR
        message += (
          f', which does not cover its configured limits {list(needed)}'
        )
  if severity == WARNING:
    message += '; make sure this covers the range the joint needs'
  return Problem(POSITION_LIMITS, report.id, message, severity)


def _motor_problems(report, robot_config, baud_rate) -> list[Problem]:
  name = label(report.id, robot_config)
  found = []

  def add(kind, message, severity=ERROR):
    found.append(Problem(kind, report.id, f'{name}: {message}', severity))

  if report.model_name is None:
    add(
      UNKNOWN_MODEL,
      f'unknown model number {report.model_number}; supported: '
      + ', '.join(f'{n} ({m[0]})' for n, m in sorted(table.MODELS.items())),
    )
  if not report.readable:
    add(
      UNREADABLE,
      'answers pings but not reads (Status Return Level 0?); '
      f'{report.read_error}',
    )
    return found
  if report.hardware_error:
    names = ', '.join(report.hardware_error_names) or 'unknown bits'
    add(
      HARDWARE_ERROR,
      f'hardware error {names} (0x{report.hardware_error:02x}); reboot the '
      'motor (power cycle or Reboot instruction) after removing the cause',
    )
  mode = report.operating_mode
  if mode != table.POSITION_MODE:
    add(
      OPERATING_MODE,
      f'operating mode {mode} ({table.OPERATING_MODES.get(mode, "unknown")});'
      f' ROBEL needs position mode ({table.POSITION_MODE})',
    )
  if report.return_delay_time:
    delay = report.return_delay_us
    add(
      RETURN_DELAY,
      f'return delay time {report.return_delay_time} ({delay} us): each of '
      f'its replies, and so every sync read of the robot, waits {delay} us '
      'longer; set it to 0',
    )
  if report.status_return_level != 2:
    add(
      STATUS_RETURN_LEVEL,
      f'status return level {report.status_return_level}: writes are not '
      'answered, so they time out and their errors go unseen; set it to 2',
    )
  if report.baud_rate != baud_rate:
    add(
      BAUD_RATE,
      f'baud rate register {report.baud_register} '
      f'({format_baud(report.baud_rate)}) differs from the bus rate '
      f'{format_baud(baud_rate)}',
    )
  limits = _limit_problem(report, robot_config)
  if limits is not None:
    found.append(limits)
  return found


def _format_ids(ids: Iterable[int]) -> str:
  """'10-12, 20, 50': sorted IDs, runs of consecutive ones as ranges."""
  runs: list[list[int]] = []
  for motor_id in sorted(set(ids)):
    if runs and motor_id == runs[-1][1] + 1:
      runs[-1][1] = motor_id
    else:
      runs.append([motor_id, motor_id])
  return ', '.join(
    str(first) if first == last else f'{first}-{last}' for first, last in runs
  )


def _no_motors(expected: Sequence[int], baud_rate: int, all_ids: bool) -> str:
  """What a scan that found no motor tried, and how to try otherwise."""
  if all_ids or not expected:
    tried, more = f'every ID 0-{MAX_ID}', ''
  else:
    tried, more = f'ID(s) {_format_ids(expected)}', ', or every ID (--all_ids)'
  others = [rate for rate in table.BAUD_RATES.values() if rate != baud_rate]
  factory = table.BAUD_RATES[1]  # Dynamixel X motors leave the factory so.
  default = f' ({factory}: new motors)' if baud_rate != factory else ''
  return (
    f'bus: no motor answered at {format_baud(baud_rate)} (tried {tried}); '
    'check power and wiring, then try another rate with --baud=RATE, one '
    f'of {", ".join(map(str, others))}{default}{more}'
  )


def problems(
  reports: Sequence[MotorReport],
  robot_config: config_lib.RobotConfig | None = None,
  baud_rate: int = table.DEFAULT_BAUD_RATE,
  ids: Iterable[int] = (),
  all_ids: bool = False,
) -> list[Problem]:
  """What is wrong with the scanned motors, for ROBEL.

  Args:
    reports: the scan.
    robot_config: the robot the bus should carry (None: no expectation).
    baud_rate: the rate the bus was scanned at, bits per second.
    ids: further motors expected on the bus.
    all_ids: whether every ID was scanned (as it is when none is expected).

  Returns:
    Problems, ERROR ones decide the exit status; bus-wide ones first, then
    by motor ID.
  """
  ids = set(ids)
  found = {report.id: report for report in reports}
  expected = expected_ids(robot_config, ids)
  bus_problems = []
  if robot_config is not None and robot_config.baud_rate != baud_rate:
    bus_problems.append(
      Problem(
        BAUD_RATE,
        None,
        f'bus: scanned at {format_baud(baud_rate)} but the configuration '
        f'({robot_config.source}) uses {format_baud(robot_config.baud_rate)}',
      )
    )
  if not found:  # Nothing to check is a failure too (a wrong baud rate).
    bus_problems.append(
      Problem(NO_MOTORS, None, _no_motors(expected, baud_rate, all_ids))
    )
  motor_problems = _missing_problems(found, robot_config, ids)
  for report in reports:
    if expected and report.id not in expected:
      where = 'the configuration' if robot_config is not None else '--ids'
      motor_problems.append(
        Problem(
          EXTRA,
          report.id,
          f'motor {report.id}: on the bus but not in {where}',
        )
      )
    motor_problems += _motor_problems(report, robot_config, baud_rate)
  motor_problems.sort(key=lambda problem: problem.motor_id)
  return bus_problems + motor_problems


def errors(found: Iterable[Problem]) -> list[Problem]:
  """The problems that count for the exit status."""
  return [problem for problem in found if problem.severity == ERROR]
