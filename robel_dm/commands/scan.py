"""Diagnostics of a Dynamixel bus: which motors answer, how they are set up.

  robel-scan --device_path=/dev/ttyUSB0 --robot=dclaw

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

from collections.abc import Sequence
import sys

from absl import app, flags

from robel_dm import command_help, robots
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.scan.cli import (
  ScanOptions,
  UsageError,
  load_config,
  parse_ids,
  run,
)


def _define_flags():
  device_path = flags.DEFINE_string(
    'device_path',
    None,
    'Serial device of the bus, e.g. /dev/ttyUSB0 (the flag the other '
    'commands give a robot by).',
  )
  # --device, the flag's first name, still works.
  flags.DEFINE_alias('device', 'device_path')
  return {
    'device_path': device_path,
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
  """The command (`robel-scan`); exits with its status."""

  flag_values = _define_flags()
  command_help.set_help(__doc__, __name__)

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
      if not values['device_path']:
        raise UsageError(
          '--device_path is required, e.g. --device_path=/dev/ttyUSB0'
        )
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
    return run(values['device_path'], options)

  app.run(run_flags, argv=argv, flags_parser=parse)


if __name__ == '__main__':
  main()
