"""Diagnostics of a Dynamixel bus: which motors answer, how they are set up.

  python -m robel_dm.hardware.scan --device=/dev/ttyUSB0 --robot=dclaw

finds the motors (pings; with `--all_ids` a Broadcast Ping covers every ID),
lists what each reports (model, firmware, position, temperature, voltage,
operating mode, baud rate, return delay, status return level, position
limits, torque, hardware errors) and flags what would trouble ROBEL: missing
or unexpected motors, unknown models, modes other than position control,
return delays that cost bus time, a status return level below 2, a baud
register that differs from the bus, narrowed position limits and latched
hardware errors. With `--apply` it offers, motor by motor, to write ROBEL's
settings (operating mode 3, return delay 0, status return level 2) and reads
them back.

Without a robot configuration or `--ids` every ID is scanned and nothing is
expected. Exit status: 0 without problems, 1 if problems were found (or
remain after `--apply`), 2 for usage and connection errors. Warnings (e.g.
narrowed position limits) are listed but do not change the exit status.

The functions return data (`scan`, `problems`, `recommended_writes`,
`apply_fixes`); `run` is the command line without flag parsing.
"""

from collections.abc import Callable, Iterable, Sequence
import contextlib
import dataclasses
import sys
from typing import TextIO

from robel_dm.hardware import config as config_lib
from robel_dm.hardware import control_table as table
from robel_dm.hardware import dynamixel

MAX_ID = 252
ALL_IDS = tuple(range(MAX_ID + 1))
_FULL_POSITION_RANGE = (0, 4_095)

# What ROBEL needs (docs/dynamixel.md sections 1.6 and 2).
RECOMMENDED = {
  'status_return_level': 2,
  'operating_mode': table.POSITION_MODE,
  'return_delay_time': 0,
}
_US_PER_RETURN_DELAY_UNIT = 2

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

# The two blocks a motor is read in: 0..70 (EEPROM and the RAM items up to
# Hardware Error Status) and 132..146 (present position to temperature).
_BLOCKS = (
  (table.MODEL_NUMBER.address, table.HARDWARE_ERROR_STATUS.address + 1),
  (table.PRESENT_POSITION.address, table.PRESENT_TEMPERATURE.address + 1),
)
_ITEMS = {
  'firmware': table.FIRMWARE_VERSION,
  'baud_register': table.BAUD_RATE,
  'return_delay_time': table.RETURN_DELAY_TIME,
  'operating_mode': table.OPERATING_MODE,
  'max_position_limit': table.MAX_POSITION_LIMIT,
  'min_position_limit': table.MIN_POSITION_LIMIT,
  'torque_enable': table.TORQUE_ENABLE,
  'status_return_level': table.STATUS_RETURN_LEVEL,
  'hardware_error': table.HARDWARE_ERROR_STATUS,
  'position': table.PRESENT_POSITION,
  'input_voltage_raw': table.PRESENT_INPUT_VOLTAGE,
  'temperature': table.PRESENT_TEMPERATURE,
}
# Names of the items `--apply` writes (control_table has none).
_ITEM_NAMES = {
  'status_return_level': 'Status Return Level',
  'operating_mode': 'Operating Mode',
  'return_delay_time': 'Return Delay Time',
}


class UsageError(ValueError):
  """A bad command line (exit status 2)."""


@dataclasses.dataclass(frozen=True)
class MotorReport:
  """What one motor reports; register fields are None if unreadable.

  Attributes:
    id: Dynamixel ID.
    model_number: from the ping.
    firmware: Firmware Version.
    position: Present Position, ticks.
    temperature: Present Temperature, deg C.
    input_voltage_raw: Present Input Voltage, 0.1 V.
    operating_mode: Operating Mode register.
    baud_register: Baud Rate register (0..7).
    return_delay_time: Return Delay Time register, 2 us.
    status_return_level: Status Return Level (0..2).
    min_position_limit: Min Position Limit, ticks.
    max_position_limit: Max Position Limit, ticks.
    torque_enable: Torque Enable (0 or 1).
    hardware_error: Hardware Error Status bits.
    read_error: why the registers could not be read (None if they were).
  """

  id: int
  model_number: int
  firmware: int | None = None
  position: int | None = None
  temperature: int | None = None
  input_voltage_raw: int | None = None
  operating_mode: int | None = None
  baud_register: int | None = None
  return_delay_time: int | None = None
  status_return_level: int | None = None
  min_position_limit: int | None = None
  max_position_limit: int | None = None
  torque_enable: int | None = None
  hardware_error: int | None = None
  read_error: str | None = None

  @property
  def readable(self) -> bool:
    return self.read_error is None

  @property
  def model_name(self) -> str | None:
    """The model's name, None for an unknown model number."""
    model = table.MODELS.get(self.model_number)
    return model[0] if model else None

  @property
  def position_rad(self) -> float | None:
    """Motor angle, rad (ticks * 2 pi / 4096)."""
    if self.position is None:
      return None
    return self.position * table.RADIANS_PER_TICK

  @property
  def input_voltage(self) -> float | None:
    """Input voltage, V."""
    if self.input_voltage_raw is None:
      return None
    return self.input_voltage_raw * table.VOLTS_PER_UNIT

  @property
  def return_delay_us(self) -> int | None:
    if self.return_delay_time is None:
      return None
    return self.return_delay_time * _US_PER_RETURN_DELAY_UNIT

  @property
  def baud_rate(self) -> int | None:
    """Bits per second the Baud Rate register selects (None if unknown)."""
    return table.BAUD_RATES.get(self.baud_register)

  @property
  def torque_enabled(self) -> bool | None:
    return None if self.torque_enable is None else bool(self.torque_enable)

  @property
  def hardware_error_names(self) -> list[str]:
    return table.hardware_error_names(self.hardware_error or 0)


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


@dataclasses.dataclass(frozen=True)
class Write:
  """One register write `--apply` proposes.

  Attributes:
    field: the MotorReport field (a key of RECOMMENDED).
    item: the control-table item.
    value: the value to write.
    current: the value now (None if unknown).
  """

  field: str
  item: table.Item
  value: int
  current: int | None

  def describe(self) -> str:
    name = _ITEM_NAMES[self.field]
    return (
      f'{name} (address {self.item.address}): '
      f'{_describe_value(self.field, self.current)} -> '
      f'{_describe_value(self.field, self.value)}'
    )


@dataclasses.dataclass(frozen=True)
class FixResult:
  """The outcome of `--apply` on one motor.

  Attributes:
    motor_id: the motor.
    writes: the writes proposed.
    applied: whether they were written (False: declined or not possible).
    failures: what did not take (empty if everything was read back right).
  """

  motor_id: int
  writes: tuple[Write, ...]
  applied: bool
  failures: tuple[str, ...] = ()

  @property
  def ok(self) -> bool:
    return self.applied and not self.failures


def _describe_value(field: str, value: int | None) -> str:
  if value is None:
    return '?'
  if field == 'operating_mode':
    return f'{value} ({table.OPERATING_MODES.get(value, "unknown")})'
  if field == 'return_delay_time':
    return f'{value} ({value * _US_PER_RETURN_DELAY_UNIT} us)'
  return str(value)


# --- Finding and reading motors -----------------------------------------------


def open_bus(
  device_path: str,
  baud_rate: int = table.DEFAULT_BAUD_RATE,
  retries: int = 2,
) -> dynamixel.DynamixelClient:
  """Opens a port for probing (no motor is required; torque is untouched).

  Raises:
    dynamixel.DynamixelError: if the device cannot be opened.
    ValueError: for a baud rate that Dynamixel servos do not support.
  """
  client = dynamixel.DynamixelClient(
    device_path, ALL_IDS, baud_rate=baud_rate, retries=retries
  )
  client.connect(check_motors=False)
  return client


def find_motors(
  client: dynamixel.DynamixelClient,
  ids: Iterable[int] = (),
  all_ids: bool = False,
) -> dict[int, int]:
  """Finds which motors answer.

  Args:
    client: a connected client.
    ids: IDs to ping one by one.
    all_ids: also find every other ID with one Broadcast Ping (~0.8 s, where
      pinging 253 absent IDs one by one would take 253 timeouts).

  Returns:
    Motor ID -> model number, by ID.
  """
  found = {}
  if all_ids:
    found = {i: model for i, (model, _) in client.broadcast_ping().items()}
  for motor_id in ids:
    if motor_id not in found:
      with contextlib.suppress(dynamixel.MissingMotorError):
        found[motor_id] = client.ping(motor_id)
  return dict(sorted(found.items()))


def _decode(item: table.Item, raw: bytes) -> int:
  value = int.from_bytes(raw, 'little')
  return table.to_signed(value, item.size) if item.signed else value


def _read_fields(client, motor_id: int) -> dict[str, int]:
  """Reads the report's registers in two block reads.

  Falls back to one read per item if a block read is refused (firmware
  that does not allow reading across reserved addresses).
  """
  try:
    blocks = [
      (start, client.read_bytes(motor_id, start, end - start))
      for start, end in _BLOCKS
    ]
  except dynamixel.MissingMotorError:
    raise
  except dynamixel.DynamixelError:
    return {
      field: client.read_register(item, [motor_id])[motor_id]
      for field, item in _ITEMS.items()
    }
  fields = {}
  for field, item in _ITEMS.items():
    for start, data in blocks:
      offset = item.address - start
      if offset >= 0 and offset + item.size <= len(data):
        fields[field] = _decode(item, data[offset : offset + item.size])
        break
  return fields


def read_motor(
  client: dynamixel.DynamixelClient, motor_id: int, model_number: int
) -> MotorReport:
  """Reads one motor's registers into a report (never raises for the motor).

  A motor that answers pings but not reads (Status Return Level 0, or it
  went away) gets a report with `read_error` set.
  """
  try:
    fields = _read_fields(client, motor_id)
  except dynamixel.DynamixelError as error:
    return MotorReport(motor_id, model_number, read_error=str(error))
  return MotorReport(motor_id, model_number, **fields)


def scan(
  client_or_device: dynamixel.DynamixelClient | str,
  ids: Iterable[int] = (),
  all_ids: bool = False,
  baud_rate: int = table.DEFAULT_BAUD_RATE,
) -> list[MotorReport]:
  """Finds the motors and reads each.

  Args:
    client_or_device: a connected client, or a device path to open (at
      `baud_rate`) for the scan.
    ids: IDs to ping one by one.
    all_ids: also find every other ID (Broadcast Ping).
    baud_rate: bits per second, when a device path is given.

  Returns:
    One report per motor found, by ID.

  Raises:
    dynamixel.DynamixelError: if a device path cannot be opened.
  """
  if isinstance(client_or_device, str):
    client = open_bus(client_or_device, baud_rate)
    try:
      return scan(client, ids, all_ids)
    finally:
      client.disconnect()
  client = client_or_device
  found = find_motors(client, ids, all_ids)
  return [read_motor(client, i, model) for i, model in found.items()]


# --- Problems -----------------------------------------------------------------


def _motors(robot_config: config_lib.RobotConfig | None):
  if robot_config is None:
    return {}
  return {m.id: m for m in robot_config.joints + robot_config.auxiliary}


def expected_ids(
  robot_config: config_lib.RobotConfig | None, ids: Iterable[int] = ()
) -> list[int]:
  """The motors a scan looks for: the configuration's and `ids`."""
  return sorted(set(_motors(robot_config)) | set(ids))


def label(
  motor_id: int, robot_config: config_lib.RobotConfig | None = None
) -> str:
  """'motor 10 (FFJ10)', or 'motor 99' for a motor not in the config."""
  motor = _motors(robot_config).get(motor_id)
  return f'motor {motor_id} ({motor.name})' if motor else f'motor {motor_id}'


def _format_baud(bits_per_second: int | None) -> str:
  if bits_per_second is None:
    return '?'
  return f'{bits_per_second:,} bps'


def _missing_problems(found, robot_config, ids) -> list[Problem]:
  problems_ = []
  motors = _motors(robot_config)
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
  motor = _motors(robot_config).get(report.id)
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
      f'({_format_baud(report.baud_rate)}) differs from the bus rate '
      f'{_format_baud(baud_rate)}',
    )
  limits = _limit_problem(report, robot_config)
  if limits is not None:
    found.append(limits)
  return found


def problems(
  reports: Sequence[MotorReport],
  robot_config: config_lib.RobotConfig | None = None,
  baud_rate: int = table.DEFAULT_BAUD_RATE,
  ids: Iterable[int] = (),
) -> list[Problem]:
  """What is wrong with the scanned motors, for ROBEL.

  Args:
    reports: the scan.
    robot_config: the robot the bus should carry (None: no expectation).
    baud_rate: the rate the bus was scanned at, bits per second.
    ids: further motors expected on the bus.

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
        f'bus: scanned at {_format_baud(baud_rate)} but the configuration '
        f'({robot_config.source}) uses {_format_baud(robot_config.baud_rate)}',
      )
    )
  if expected and not found:
    bus_problems.append(
      Problem(
        NO_MOTORS,
        None,
        f'bus: no motor answered at {_format_baud(baud_rate)}; check power, '
        'wiring and the baud rate (--baud), or scan every ID (--all_ids)',
      )
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


# --- Applying ROBEL's settings ------------------------------------------------


def recommended_writes(report: MotorReport) -> list[Write]:
  """The writes that give a motor ROBEL's settings, in the order to apply.

  Status Return Level (RAM) comes first: below 2 the other writes would not
  be answered. A motor that does not answer reads only gets that write
  (its other registers are unknown); an unknown model gets none.
  """
  if report.model_name is None:
    return []
  writes = []
  if report.status_return_level != RECOMMENDED['status_return_level']:
    writes.append(
      Write(
        'status_return_level',
        table.STATUS_RETURN_LEVEL,
        RECOMMENDED['status_return_level'],
        report.status_return_level,
      )
    )
  if not report.readable:
    return writes
  for field, item in (
    ('operating_mode', table.OPERATING_MODE),
    ('return_delay_time', table.RETURN_DELAY_TIME),
  ):
    current = getattr(report, field)
    if current != RECOMMENDED[field]:
      writes.append(Write(field, item, RECOMMENDED[field], current))
  return writes


def apply_fixes(
  client: dynamixel.DynamixelClient,
  reports: Sequence[MotorReport],
  confirm: Callable[[MotorReport, list[Write]], bool],
  log: Callable[[str], None] = print,
  robot_config: config_lib.RobotConfig | None = None,
) -> list[FixResult]:
  """Writes ROBEL's settings to each motor that needs them and agrees.

  EEPROM items need the torque off: it is turned off first (and left off),
  which `log` reports. Every write is read back.

  Args:
    client: a connected client.
    reports: the motors to consider.
    confirm: asked once per motor with the writes it needs; a motor is only
      touched if it returns True.
    log: receives a line for everything done.
    robot_config: names the motors in messages.

  Returns:
    One result per round of writes a motor needed (two for a motor that
    only answered reads once its status return level was fixed).
  """
  results = []
  for report in reports:
    name = label(report.id, robot_config)
    while writes := recommended_writes(report):
      if not confirm(report, writes):
        log(f'{name}: left unchanged')
        results.append(FixResult(report.id, tuple(writes), False))
        break
      failures = _apply(client, report, writes, log, name)
      results.append(FixResult(report.id, tuple(writes), True, tuple(failures)))
      if failures:
        log(f'{name}: FAILED: ' + '; '.join(failures))
        break
      log(f'{name}: written and read back')
      if report.readable:
        break
      # It answers reads now: see what else it needs.
      report = read_motor(client, report.id, report.model_number)
      if not report.readable:
        break
  return results


def _apply(client, report, writes, log, name) -> list[str]:
  motor_id = report.id
  ram = [write for write in writes if not write.item.eeprom]
  eeprom = [write for write in writes if write.item.eeprom]
  try:
    for write in ram:
      if write.item == table.STATUS_RETURN_LEVEL:
        # Below level 2 the write is executed but not answered (a timeout):
        # the read-back below tells whether it took.
        with contextlib.suppress(dynamixel.DynamixelError):
          client.write_register(write.item, {motor_id: write.value})
      else:
        client.write_register(write.item, {motor_id: write.value})
    if eeprom and report.torque_enable != 0:
      log(
        f'{name}: turning torque off (EEPROM items can only be written with '
        'torque off); it stays off'
      )
      client.set_torque([motor_id], False)
    for write in eeprom:
      client.write_register(write.item, {motor_id: write.value})
    failures = []
    for write in writes:
      value = client.read_register(write.item, [motor_id])[motor_id]
      if value != write.value:
        failures.append(
          f'{_ITEM_NAMES[write.field]} reads {value}, not {write.value}'
        )
    return failures
  except dynamixel.DynamixelError as error:
    return [str(error)]


# --- Output -------------------------------------------------------------------


def _format_rate(bits_per_second: int | None) -> str:
  if bits_per_second is None:
    return '?'
  if bits_per_second >= 1_000_000:
    return f'{bits_per_second / 1_000_000:g}M'
  return f'{bits_per_second / 1_000:g}k'


def _row(report: MotorReport, robot_config) -> list[str]:
  motor = _motors(robot_config).get(report.id)
  model = f'{report.model_name or "unknown"} ({report.model_number})'
  row = [str(report.id), motor.name if motor else '-', model]
  if not report.readable:
    return row + ['?'] * 10 + ['(no answer to reads)']
  mode = report.operating_mode
  errors_ = report.hardware_error_names
  row += [
    str(report.firmware),
    f'{report.position} ({report.position_rad:+.3f} rad)',
    f'{report.temperature} C',
    f'{report.input_voltage:.1f} V',
    f'{mode} {table.OPERATING_MODES.get(mode, "unknown")}',
    f'{report.baud_register} ({_format_rate(report.baud_rate)})',
    f'{report.return_delay_us} us',
    str(report.status_return_level),
    f'{report.min_position_limit}..{report.max_position_limit}',
    'on' if report.torque_enabled else 'off',
    ', '.join(errors_) if errors_ else '-',
  ]
  return row


_HEADER = [
  'ID', 'joint', 'model', 'fw', 'position', 'temp', 'input', 'mode',
  'baud', 'delay', 'SRL', 'limits', 'torque', 'hardware error',
]  # fmt: skip


def format_table(
  reports: Sequence[MotorReport],
  robot_config: config_lib.RobotConfig | None = None,
) -> str:
  """The reports as a text table, one motor per line."""
  if not reports:
    return '(no motors found)'
  rows = [_HEADER] + [_row(report, robot_config) for report in reports]
  widths = [max(len(row[i]) for row in rows) for i in range(len(_HEADER))]
  lines = [
    '  '.join(
      cell.ljust(width) for cell, width in zip(row, widths, strict=True)
    ).rstrip()
    for row in rows
  ]
  lines.insert(1, '  '.join('-' * width for width in widths))
  return '\n'.join(lines)


def summary(
  reports: Sequence[MotorReport],
  found_problems: Sequence[Problem],
  device_path: str,
  baud_rate: int,
) -> str:
  """One line: motors found, problems and warnings."""
  count = len(errors(found_problems))
  warnings = len(found_problems) - count
  verdict = 'OK' if not count else 'PROBLEMS'
  return (
    f'{verdict}: {len(reports)} motor(s) found on {device_path} at '
    f'{_format_baud(baud_rate)}; {count} problem(s), {warnings} warning(s)'
  )


# --- Command line -------------------------------------------------------------


def parse_ids(text: str | Sequence[str] | None) -> list[int]:
  """Parses '10,11,20-22' (or a list of such parts) into IDs.

  Raises:
    UsageError: for anything that is not an ID 0..252 or a range of them.
  """
  if not text:
    return []
  parts = text.split(',') if isinstance(text, str) else list(text)
  ids = set()
  for part in (p.strip() for p in parts):
    if not part:
      continue
    try:
      if '-' in part:
        first, last = (int(x) for x in part.split('-', 1))
        values = range(first, last + 1)
      else:
        values = [int(part)]
    except ValueError:
      raise UsageError(f'--ids: {part!r} is not an ID or a range') from None
    if not values or not all(0 <= v <= MAX_ID for v in values):
      raise UsageError(f'--ids: {part!r} is outside 0..{MAX_ID}')
    ids.update(values)
  return sorted(ids)


def load_config(
  robot: str | None, robot_config_path: str | None
) -> config_lib.RobotConfig | None:
  """The configuration from --robot or --robot_config (None if neither).

  Raises:
    UsageError: if both are given or the configuration is not valid.
  """
  if robot and robot_config_path:
    raise UsageError('give --robot or --robot_config, not both')
  try:
    if robot_config_path:
      return config_lib.load(robot_config_path)
    if robot:
      return config_lib.default(robot)
  except config_lib.ConfigError as error:
    raise UsageError(str(error)) from None
  return None


def _ask(answers: TextIO, out: TextIO) -> Callable[[str], bool]:
  def ask(question: str) -> bool:
    out.write(f'{question} [y/N] ')
    out.flush()
    answer = answers.readline()
    if not answer:
      out.write('\n(no answer: no)\n')
    return answer.strip().lower() in ('y', 'yes')

  return ask


def _report(out, reports, found_problems, robot_config, device, baud_rate):
  print(format_table(reports, robot_config), file=out)
  if found_problems:
    print('', file=out)
    for problem in found_problems:
      print(problem, file=out)
  print('', file=out)
  print(summary(reports, found_problems, device, baud_rate), file=out)


def run(
  device: str,
  robot_config: config_lib.RobotConfig | None = None,
  baud_rate: int | None = None,
  ids: Iterable[int] = (),
  all_ids: bool = False,
  apply: bool = False,
  yes: bool = False,
  answers: TextIO | None = None,
  out: TextIO | None = None,
  err: TextIO | None = None,
) -> int:
  """The command line after flag parsing: scans, prints, maybe applies.

  Args:
    device: serial device, e.g. '/dev/ttyUSB0'.
    robot_config: the robot the bus should carry, or None.
    baud_rate: bits per second; default the configuration's (or 1 Mbps).
    ids: further motors to look for.
    all_ids: scan every ID (also done without a configuration and `ids`).
    apply: offer to write ROBEL's settings to misconfigured motors.
    yes: write them without asking.
    answers: where the answers to the questions come from (stdin).
    out: where the listing goes (stdout).
    err: where error messages go (stderr).

  Returns:
    The exit status: 0 no problems, 1 problems (left), 2 usage or
    connection error.
  """
  answers = sys.stdin if answers is None else answers
  out = sys.stdout if out is None else out
  err = sys.stderr if err is None else err
  if baud_rate is None:
    baud_rate = (
      robot_config.baud_rate if robot_config else table.DEFAULT_BAUD_RATE
    )
  ids = sorted(set(ids))
  candidates = expected_ids(robot_config, ids)
  all_ids = all_ids or not candidates
  try:
    client = open_bus(device, baud_rate)
  except (dynamixel.DynamixelError, ValueError, ImportError) as error:
    print(f'error: {error}', file=err)
    return 2
  try:
    what = (
      f'{len(candidates)} expected ID(s)' if candidates else 'no expected IDs'
    )
    scope = ', and every ID (Broadcast Ping)' if all_ids else ''
    print(
      f'Scanning {device} at {_format_baud(baud_rate)}: {what}{scope}',
      file=out,
    )
    reports = scan(client, candidates, all_ids)
    found_problems = problems(reports, robot_config, baud_rate, ids)
    _report(out, reports, found_problems, robot_config, device, baud_rate)
    if not apply:
      return 1 if errors(found_problems) else 0
    # Only the expected motors are touched (every motor if none expected).
    targets = [r for r in reports if not candidates or r.id in candidates]
    for report in reports:
      if report not in targets and recommended_writes(report):
        print(
          f'{label(report.id, robot_config)}: not expected here, not '
          'touched (add it with --ids to include it)',
          file=out,
        )
    ask = _ask(answers, out)

    def confirm(report: MotorReport, writes: list[Write]) -> bool:
      name = label(report.id, robot_config)
      print(f'\n{name}: will write', file=out)
      for write in writes:
        print(f'  {write.describe()}', file=out)
      if any(w.item.eeprom for w in writes) and report.torque_enable != 0:
        print(
          '  torque is on: it will be turned off first and left off',
          file=out,
        )
      if yes:
        print('  (--yes: writing)', file=out)
        return True
      return ask(f'Write these to {name}?')

    results = apply_fixes(
      client,
      targets,
      confirm,
      lambda line: print(line, file=out),
      robot_config,
    )
    if not results:
      print('\n--apply: nothing to write', file=out)
      return 1 if errors(found_problems) else 0
    print('\nAfter --apply:', file=out)
    reports = scan(client, candidates, all_ids)
    found_problems = problems(reports, robot_config, baud_rate, ids)
    _report(out, reports, found_problems, robot_config, device, baud_rate)
    return 1 if errors(found_problems) else 0
  except dynamixel.DynamixelError as error:
    print(f'error: {error}', file=err)
    return 2
  finally:
    client.disconnect()


def _define_flags():
  from absl import flags  # Command line only.

  return {
    'device': flags.DEFINE_string(
      'device', None, 'Serial device of the bus, e.g. /dev/ttyUSB0.'
    ),
    'robot': flags.DEFINE_enum(
      'robot',
      None,
      ['dclaw', 'dkitty'],
      "Expect this robot's shipped configuration.",
    ),
    'robot_config': flags.DEFINE_string(
      'robot_config', None, 'Expect the robot of this configuration (JSON).'
    ),
    'baud': flags.DEFINE_integer(
      'baud',
      None,
      "Bus rate, bits per second (default: the configuration's, 1000000).",
    ),
    'ids': flags.DEFINE_string(
      'ids', None, 'Further motor IDs to expect, e.g. 10,11,20-22.'
    ),
    'all_ids': flags.DEFINE_bool(
      'all_ids', False, 'Also find every other ID (0..252; ~0.8 s).'
    ),
    'apply': flags.DEFINE_bool(
      'apply',
      False,
      'Offer to write operating mode 3, return delay 0 and status return '
      'level 2 to misconfigured motors, asking per motor.',
    ),
    'yes': flags.DEFINE_bool(
      'yes', False, 'With --apply: write without asking.'
    ),
  }


def main(argv: Sequence[str] | None = None) -> None:
  """Runs the command line; exits with its status."""
  from absl import app, flags  # Command line only.

  flag_values = _define_flags()

  def parse(args: Sequence[str]) -> list[str]:
    try:
      return flags.FLAGS(args)
    except flags.Error as error:
      print(f'error: {error}', file=sys.stderr)
      sys.exit(2)

  def run_flags(args: Sequence[str]) -> int:
    values = {name: flag.value for name, flag in flag_values.items()}
    try:
      if len(args) > 1:
        raise UsageError(f'unexpected arguments: {args[1:]}')
      if not values['device']:
        raise UsageError('--device is required, e.g. --device=/dev/ttyUSB0')
      if values['yes'] and not values['apply']:
        raise UsageError('--yes only goes with --apply')
      robot_config = load_config(values['robot'], values['robot_config'])
      ids = parse_ids(values['ids'])
      baud = values['baud']
      if baud is not None and baud not in table.BAUD_RATES.values():
        raise UsageError(
          f'--baud={baud} is not a Dynamixel rate: '
          f'{sorted(table.BAUD_RATES.values())}'
        )
    except UsageError as error:
      print(f'error: {error}', file=sys.stderr)
      return 2
    return run(
      values['device'],
      robot_config,
      baud,
      ids,
      values['all_ids'],
      values['apply'],
      values['yes'],
    )

  app.run(run_flags, argv=argv, flags_parser=parse)


if __name__ == '__main__':
  main()
