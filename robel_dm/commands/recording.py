"""Lists a recording, or exports it as a LeRobotDataset.

robel-recording DIR
robel-recording DIR --lerobot=OUT [--lerobot_version=v2.1]
"""

import argparse
from collections.abc import Sequence
import sys
import warnings

from robel_dm.recording import format as format_lib
from robel_dm.recording import lerobot, reader


def _with_warnings_as_lines(function, *args):
  """`function(*args)`, each warning it gives (a damaged file, named: see
  reader.read) printed as one line."""
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter('always')
    try:
      return function(*args)
    finally:
      for warning in caught:
        print(f'warning: {warning.message}', file=sys.stderr)


def _summary(directory: str) -> None:
  rows = _with_warnings_as_lines(reader.summarize, directory)
  # Violations after the reset, as robel-evaluate counts them.
  print(f'{"episode":>7} {"steps":>6} {"complete":>8} {"success":>7} '
        f'{"return":>10}  pos/vel/cur violations')  # fmt: skip
  for row in rows:
    safety = '/'.join(f'{v:g}' for v in row['safety'] or [])
    print(
      f'{row["episode"]:>7} {row["steps"]:>6} '
      f'{"yes" if row["complete"] else "partial":>8} '
      f'{"yes" if row["success"] else "no":>7} {row["return"]:>10.2f}  '
      f'{safety}'
    )
  print(f'{len(rows)} episodes, {sum(r["steps"] for r in rows)} steps')


def main(argv: Sequence[str] | None = None) -> int:
  """The command (`robel-recording`); `argv` without the program's name."""
  parser = argparse.ArgumentParser(
    prog='robel-recording', description=__doc__.splitlines()[0]
  )
  parser.add_argument('directory', help='a recording directory')
  parser.add_argument(
    '--lerobot',
    metavar='OUT',
    help='write its complete episodes as a LeRobotDataset here',
  )
  parser.add_argument(
    '--lerobot_version',
    choices=lerobot.VERSIONS,
    default=lerobot.VERSIONS[0],
    help='the LeRobotDataset codebase version: v3.0 (LeRobot 0.4 and '
    'later) or v2.1 (LeRobot 0.3)',
  )
  arguments = parser.parse_args(argv)
  try:
    if arguments.lerobot:
      info = _with_warnings_as_lines(
        lerobot.export,
        arguments.directory,
        arguments.lerobot,
        arguments.lerobot_version,
      )
      print(
        f'wrote {arguments.lerobot}: {info["total_episodes"]} episodes, '
        f'{info["total_frames"]} frames (LeRobotDataset '
        f'{info["codebase_version"]})'
      )
    else:
      _summary(arguments.directory)
  except format_lib.RecordingError as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  return 0


if __name__ == '__main__':
  sys.exit(main())
