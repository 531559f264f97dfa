"""Lists a recording: python -m robel_dm.recording DIR."""

import sys

from robel_dm.recording import format as format_lib


def main(argv: list[str]) -> int:
  if len(argv) != 2:
    print('usage: python -m robel_dm.recording DIR', file=sys.stderr)
    return 2
  try:
    rows = format_lib.summarize(argv[1])
  except format_lib.RecordingError as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
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
  return 0


if __name__ == '__main__':
  sys.exit(main(sys.argv))
