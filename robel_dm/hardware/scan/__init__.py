"""Diagnostics of a Dynamixel bus: which motors answer, how they are set up.

`robel-scan --device_path=/dev/ttyUSB0 --robot=dclaw`
checks a bus (`cli` describes the command). The functions return data:
`probe.scan` reads the motors into `MotorReport`s, `checks.problems` says
what would trouble ROBEL, `fixes.recommended_writes` and
`fixes.apply_fixes` give motors ROBEL's settings, and `report` formats the
result as text; `cli.run` is the command line without flag parsing.
"""

from robel_dm.hardware.scan.checks import (
  BAUD_RATE,
  ERROR,
  EXTRA,
  HARDWARE_ERROR,
  MISSING,
  NO_MOTORS,
  OPERATING_MODE,
  POSITION_LIMITS,
  RETURN_DELAY,
  STATUS_RETURN_LEVEL,
  UNKNOWN_MODEL,
  UNREADABLE,
  WARNING,
  Problem,
  errors,
  expected_ids,
  label,
  problems,
)
from robel_dm.hardware.scan.cli import (
  ScanOptions,
  UsageError,
  load_config,
  parse_ids,
  run,
)
from robel_dm.hardware.scan.fixes import (
  RECOMMENDED,
  FixResult,
  Write,
  apply_fixes,
  recommended_writes,
)
from robel_dm.hardware.scan.probe import (
  ALL_IDS,
  MAX_ID,
  MotorReport,
  find_motors,
  open_bus,
  read_motor,
  scan,
)
from robel_dm.hardware.scan.report import format_report, format_table, summary

__all__ = [
  'ALL_IDS',
  'BAUD_RATE',
  'ERROR',
  'EXTRA',
  'HARDWARE_ERROR',
  'MAX_ID',
  'MISSING',
  'NO_MOTORS',
  'OPERATING_MODE',
  'POSITION_LIMITS',
  'RECOMMENDED',
  'RETURN_DELAY',
  'STATUS_RETURN_LEVEL',
  'UNKNOWN_MODEL',
  'UNREADABLE',
  'WARNING',
  'FixResult',
  'MotorReport',
  'Problem',
  'ScanOptions',
  'UsageError',
  'Write',
  'apply_fixes',
  'errors',
  'expected_ids',
  'find_motors',
  'format_report',
  'format_table',
  'label',
  'load_config',
  'open_bus',
  'parse_ids',
  'problems',
  'read_motor',
  'recommended_writes',
  'run',
  'scan',
  'summary',
]
