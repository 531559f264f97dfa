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
remain after `--apply`; no motor answering at all is one, with the IDs and
rate tried and the other rates `--baud` takes), 2 for usage and connection
errors. Warnings (e.g. narrowed position limits) are listed but do not
change the exit status.
"""

from collections.abc import Callable, Iterable, Sequence
import dataclasses
import sys
from typing import TextIO

from robel_dm import robots
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


def _define_flags():
  from absl import flags  # Command line only.

  # The flags then belong to the module that calls `main` (the package's
  # `__main__`), whose flags `--help` lists.
  flags.disclaim_key_flags()
  return {
    'device': flags.DEFINE_string(
      'device', None, 'Serial device of the bus, e.g. /dev/ttyUSB0.'
    ),
    'robot': flags.DEFINE_enum(
      'robot',
      None,
      sorted(robots.ROBOTS),
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

  from robel_dm import commands  # noqa: PLC0415 (imports absl)

  flag_values = _define_flags()
  commands.describe(__doc__, __name__)

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
    options = ScanOptions(
      robot_config=robot_config,
      baud_rate=baud,
      ids=ids,
      all_ids=values['all_ids'],
      apply=values['apply'],
      yes=values['yes'],
    )
    return run(values['device'], options)

  app.run(run_flags, argv=argv, flags_parser=parse)
