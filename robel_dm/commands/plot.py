r"""Plots evaluation results side by side: success, score and safety per task.

    robel-plot A.json [B.json ...] --output=fig.png [--labels=a,b]

Each file is the JSON that `robel-evaluate --output=...` writes (one task)
or a list of such results (a sweep); each file is one series, labelled by
the file's name or `--labels`. See `robel_dm.evaluation.plots` for the
figure and its intervals. Needs matplotlib (the `learn` extra).
"""

import argparse
from collections.abc import Sequence
import sys

from robel_dm.evaluation import plots


def main(argv: Sequence[str] | None = None) -> int:
  """The command (`robel-plot`); returns the exit status (2: an error)."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('results', nargs='+', help='evaluation JSON files')
  parser.add_argument('--output', required=True, help='image to write')
  parser.add_argument('--labels', default=None, help='comma-separated')
  args = parser.parse_args(argv)
  try:
    written = plots.plot(
      args.results,
      args.output,
      args.labels.split(',') if args.labels else None,
    )
  except (ValueError, OSError, ImportError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  print(f'wrote {written}')
  return 0


if __name__ == '__main__':
  sys.exit(main())
