"""The baseline table's command line: `robel-baselines train|list|report`
(see `robel_dm.learning.baselines`)."""

import argparse
import json
import sys

from robel_dm.learning import baselines
from robel_dm.learning.baselines import report, scheduling


def main(argv: list[str] | None = None) -> int:
  """The command (`robel-baselines`): runs train, list or report; returns
  the exit code."""
  parser = argparse.ArgumentParser(
    description=baselines.__doc__.splitlines()[0]
  )
  commands = parser.add_subparsers(dest='command', required=True)
  train_parser = commands.add_parser('train', help='run the table')
  train_parser.add_argument('--queue', type=int, default=0)
  train_parser.add_argument('--queues', type=int, default=1)
  train_parser.add_argument(
    '--only',
    default=None,
    help='fnmatch patterns of run names, comma-separated (any of them)',
  )
  train_parser.add_argument('--hours', type=float, default=None)
  train_parser.add_argument('--ray_address', default=None)
  train_parser.add_argument(
    '--force',
    action='store_true',
    help='make the chosen runs again from the start (needs --only)',
  )
  commands.add_parser('list', help='the runs and where each stands')
  commands.add_parser('report', help='docs/baselines.md, figures, policies')
  args = parser.parse_args(argv)
  try:
    if args.command == 'list':
      for run in baselines.runs():
        print(f'{run.name:50s} {baselines.status(run)}'.rstrip())
      rows = (
        json.loads(baselines.RESULTS.read_text())
        if baselines.RESULTS.is_file()
        else []
      )
      print(report.remaining(rows))
    elif args.command == 'report':
      report.write()
    elif args.ray_address:
      ignored = [
        flag
        for flag, given in (
          ('--force', args.force),
          ('--hours', args.hours is not None),
          ('--queue', args.queue != 0),
          ('--queues', args.queues != 1),
        )
        if given
      ]
      if ignored:
        raise ValueError(
          f'{", ".join(ignored)}: not with --ray_address (a cluster runs '
          'every chosen run once)'
        )
      scheduling.train_ray(args.ray_address, args.only)
    else:
      if not 0 <= args.queue < args.queues:
        raise ValueError('--queue must be in [0, --queues)')
      if args.force and not args.only:
        raise ValueError('--force makes runs again: choose them with --only')
      scheduling.train_queue(
        args.queue, args.queues, args.only, args.hours, force=args.force
      )
  except ValueError as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  return 0


if __name__ == '__main__':
  sys.exit(main())
