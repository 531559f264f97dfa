"""The bus scan without flag parsing: `run` scans a bus and reports it (and
applies ROBEL's settings with `ScanOptions.apply`), `parse_ids` and
`load_config` read what a command line gives; `robel_dm.commands.scan` is
the command over it (its docstring says what the scan checks and its exit
status).
"""

from collections.abc import Callable, Iterable, Sequence
import dataclasses
import sys
from typing import TextIO

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.scan import report as report_lib
from robel_dm.hardware.scan.checks import (
  Problem,
  errors,
  expected_ids,
  format_baud,
  label,
  problems,
)
from robel_dm.hardware.scan.fixes import (
  FixResult,
  Write,
  apply_fixes,
  recommended_writes,
)
from robel_dm.hardware.scan.probe import MAX_ID, MotorReport, open_bus, scan


class UsageError(ValueError):
  """A bad command line (exit status 2)."""


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


@dataclasses.dataclass(frozen=True)
class ScanOptions:
  """What `run` looks for, and whether it may change the motors.

  Attributes:
    robot_config: the robot the bus should carry, or None.
    baud_rate: bits per second; None: the configuration's (or 1 Mbps).
    ids: further motors to look for.
    all_ids: scan every ID (also done without a configuration and `ids`).
    apply: offer to write ROBEL's settings to misconfigured motors.
    yes: write them without asking.
  """

  robot_config: config_lib.RobotConfig | None = None
  baud_rate: int | None = None
  ids: Iterable[int] = ()
  all_ids: bool = False
  apply: bool = False
  yes: bool = False


def run(
  device: str,
  options: ScanOptions = ScanOptions(),
  answers: TextIO | None = None,
  out: TextIO | None = None,
  err: TextIO | None = None,
) -> int:
  """The command line after flag parsing: scans, prints, maybe applies.

  Args:
    device: serial device, e.g. '/dev/ttyUSB0'.
    options: what to look for and whether to apply ROBEL's settings.
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
  options = _resolved(options)
  try:
    client = open_bus(device, options.baud_rate)
  except (dynamixel.DynamixelError, ValueError, ImportError) as error:
    print(f'error: {error}', file=err)
    return 2
  try:
    candidates = expected_ids(options.robot_config, options.ids)
    what = (
      f'{len(candidates)} expected ID(s)' if candidates else 'no expected IDs'
    )
    scope = ', and every ID (Broadcast Ping)' if options.all_ids else ''
    print(
      f'Scanning {device} at {format_baud(options.baud_rate)}: {what}{scope}',
      file=out,
    )
    reports, found_problems = _scan_and_report(client, device, options, out)
    if options.apply:
      if _apply(client, reports, options, answers, out):
        print('\nAfter --apply:', file=out)
        _, found_problems = _scan_and_report(client, device, options, out)
      else:
        print('\n--apply: nothing to write', file=out)
    return 1 if errors(found_problems) else 0
  except dynamixel.DynamixelError as error:
    print(f'error: {error}', file=err)
    return 2
  finally:
    client.disconnect()


def _resolved(options: ScanOptions) -> ScanOptions:
  """`options` with the rate, the sorted IDs and whether to scan every ID
  decided (every ID when no motor is expected)."""
  robot_config = options.robot_config
  baud_rate = options.baud_rate
  if baud_rate is None:
    baud_rate = (
      robot_config.baud_rate if robot_config else table.DEFAULT_BAUD_RATE
    )
  ids = sorted(set(options.ids))
  candidates = expected_ids(robot_config, ids)
  return dataclasses.replace(
    options,
    baud_rate=baud_rate,
    ids=ids,
    all_ids=options.all_ids or not candidates,
  )


def _scan_and_report(
  client: dynamixel.DynamixelClient,
  device: str,
  options: ScanOptions,
  out: TextIO,
) -> tuple[list[MotorReport], list[Problem]]:
  """Scans the bus and prints what it found and its problems."""
  robot_config, baud_rate = options.robot_config, options.baud_rate
  candidates = expected_ids(robot_config, options.ids)
  reports = scan(client, candidates, options.all_ids)
  found_problems = problems(
    reports, robot_config, baud_rate, options.ids, options.all_ids
  )
  text = report_lib.format_report(
    reports, found_problems, robot_config, device, baud_rate
  )
  print(text, file=out)
  return reports, found_problems


def _apply(
  client: dynamixel.DynamixelClient,
  reports: list[MotorReport],
  options: ScanOptions,
  answers: TextIO,
  out: TextIO,
) -> list[FixResult]:
  """Offers ROBEL's settings to the expected motors; what was written."""
  robot_config = options.robot_config
  candidates = expected_ids(robot_config, options.ids)
  # Only the expected motors are touched (every motor if none expected).
  targets = [r for r in reports if not candidates or r.id in candidates]
  for report in reports:
    if report not in targets and recommended_writes(report):
      print(
        f'{label(report.id, robot_config)}: not expected here, not '
        'touched (add it with --ids to include it)',
        file=out,
      )
  confirm = _confirm(robot_config, options.yes, _ask(answers, out), out)
  return apply_fixes(
    client,
    targets,
    confirm,
    lambda line: print(line, file=out),
    robot_config,
  )


def _confirm(
  robot_config: config_lib.RobotConfig | None,
  yes: bool,
  ask: Callable[[str], bool],
  out: TextIO,
) -> Callable[[MotorReport, list[Write]], bool]:
  """Asks (unless `yes`) whether to write `writes` to a motor, showing
  them first."""

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

  return confirm
