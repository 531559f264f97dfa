"""Speed-up of `evaluate --workers=N` over a serial run of the same episodes.

    MUJOCO_GL=egl python benchmarks/bench_workers.py --episodes 200 --workers 2

Runs the same seeded episodes serially and with N local worker processes
(worker start-up included), checks that the records are equal, and prints
the wall times and their ratio.
"""

import argparse
import time

from robel_dm import evaluation


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--domain', default='dkitty')
  parser.add_argument('--task', default='walk_random')
  parser.add_argument('--policy', default='zero')
  parser.add_argument('--episodes', type=int, default=200)
  parser.add_argument('--workers', type=int, default=2)
  args = parser.parse_args()
  timings = {}
  results = {}
  for workers in (1, args.workers):
    start = time.perf_counter()
    results[workers] = evaluation.evaluate(evaluation.EvalConfig(
      args.domain, args.task, args.episodes, policy=args.policy, seed=0,
      workers=workers,
    ))  # fmt: skip
    timings[workers] = time.perf_counter() - start
  same = results[1]['records'] == results[args.workers]['records']
  print(
    f'{args.domain}/{args.task}, {args.episodes} episodes: serial '
    f'{timings[1]:.1f} s, {args.workers} workers '
    f'{timings[args.workers]:.1f} s, speed-up '
    f'{timings[1] / timings[args.workers]:.2f}x, identical records: {same}'
  )


if __name__ == '__main__':
  main()
