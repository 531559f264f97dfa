r"""Held-out robots: the transfer table.

    robel-zoo list
    robel-zoo evaluate [--only='dclaw_pose_*/*'] \
        [--shard=0 --shards=2]
    robel-zoo report

`evaluate` runs every shipped policy in simulation and on every zoo robot
of its domain over the (virtual) Dynamixel bus, in simulated time, and
merges one record per policy and robot into docs/zoo/transfer.json
(pairings already recorded are skipped: a cut run resumes; shards split
the work between processes). `report` writes the tables of docs/zoo.md
from that file.
"""

import argparse
import sys

from robel_dm import zoo
from robel_dm.zoo import transfer


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  commands = parser.add_subparsers(dest='command', required=True)
  commands.add_parser('list', help="the zoo's robots and what differs")
  run = commands.add_parser('evaluate', help='fill docs/zoo/transfer.json')
  run.add_argument('--only', default=None, help="fnmatch on 'policy/robot'")
  run.add_argument('--shard', type=int, default=0)
  run.add_argument('--shards', type=int, default=1)
  commands.add_parser('report', help='write the tables of docs/zoo.md')
  args = parser.parse_args(argv)
  if args.command == 'list':
    for robot in zoo.robots():
      print(f'{robot.name} ({robot.domain}): {robot.about}')
  elif args.command == 'evaluate':
    if not 0 <= args.shard < args.shards:
      parser.error('--shard must be in [0, --shards)')
    try:
      transfer.run(args.only, args.shard, args.shards)
    except ValueError as error:
      print(f'error: {error}', file=sys.stderr)
      return 2
  else:
    transfer.report()
  return 0


if __name__ == '__main__':
  sys.exit(main())
