"""Giving misconfigured motors ROBEL's settings (the scan's `--apply`).

`recommended_writes` lists the register writes a motor needs (operating
mode 3, return delay 0, status return level 2); `apply_fixes` makes them,
with the torque off for EEPROM items, and reads every write back.
"""

from collections.abc import Callable, Sequence
import contextlib
import dataclasses

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.scan.checks import label
from robel_dm.hardware.scan.probe import (
  US_PER_RETURN_DELAY_UNIT,
  MotorReport,
  read_motor,
)

# What ROBEL needs (docs/dynamixel.md sections 1.6 and 2).
RECOMMENDED = {
  'status_return_level': 2,
  'operating_mode': table.POSITION_MODE,
  'return_delay_time': 0,
}
# Names of the items `--apply` writes (control_table has none).
_ITEM_NAMES = {
  'status_return_level': 'Status Return Level',
  'operating_mode': 'Operating Mode',
  'return_delay_time': 'Return Delay Time',
}


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
    return f'{value} ({value * US_PER_RETURN_DELAY_UNIT} us)'
  return str(value)


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
