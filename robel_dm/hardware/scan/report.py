"""The scan as text: a table of the motors, the problems and a summary."""

from collections.abc import Sequence

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.scan.checks import (
  Problem,
  configured_motors,
  errors,
  format_baud,
)
from robel_dm.hardware.scan.probe import MotorReport


def _format_rate(bits_per_second: int | None) -> str:
  if bits_per_second is None:
    return '?'
  if bits_per_second >= 1_000_000:
    return f'{bits_per_second / 1_000_000:g}M'
  return f'{bits_per_second / 1_000:g}k'


def _position(report: MotorReport, motor: config_lib.Motor | None) -> str:
  """Ticks and motor angle; for a configured motor also its joint angle
  through the configuration (what an offset is calibrated against)."""
  text = f'{report.position} ({report.position_rad:+.3f} rad'
  if motor is not None:
    text += f'; joint {motor.to_joint(report.position_rad):+.3f}'
  return text + ')'


def _row(report: MotorReport, robot_config) -> list[str]:
  motor = configured_motors(robot_config).get(report.id)
  model = f'{report.model_name or "unknown"} ({report.model_number})'
  row = [str(report.id), motor.name if motor else '-', model]
  if not report.readable:
    return row + ['?'] * 10 + ['(no answer to reads)']
  mode = report.operating_mode
  errors_ = report.hardware_error_names
  row += [
    str(report.firmware),
    _position(report, motor),
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
    f'{format_baud(baud_rate)}; {count} problem(s), {warnings} warning(s)'
  )


def format_report(
  reports: Sequence[MotorReport],
  found_problems: Sequence[Problem],
  robot_config: config_lib.RobotConfig | None,
  device_path: str,
  baud_rate: int,
) -> str:
  """The table, the problems (if any) and the summary, as the scan prints."""
  lines = [format_table(reports, robot_config)]
  if found_problems:
    lines += ['', *(str(problem) for problem in found_problems)]
  lines += ['', summary(reports, found_problems, device_path, baud_rate)]
  return '\n'.join(lines)
