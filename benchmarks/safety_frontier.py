r"""Success against safety violations, per safety budget (train
--safety_budget), on one task.

    MUJOCO_GL=egl python benchmarks/safety_frontier.py --task=pose_fixed \
        --budgets=none,200,50,10 --seeds=0,1,2 [--steps=40000] \
        [--action_map=safe] [--init_from=runs/baselines/TASK_sac_seed{seed}]

Each (budget, seed) is a `train` run of the default agent with that
`--safety_budget` ('none': no budget), acting through `--action_map`
(ROBEL's map, or the safe one: `task_kwargs` `action_map`), evaluated every
`--eval_every` env steps on the task's evaluation episodes (one on a Fixed
task, whose episodes are all the same; 10 otherwise). Printed per run: the
last evaluation's success and violations per episode (all kinds summed), and
the first evaluation, if any, that meets ROBEL-safe success: success >= 0.8
with at most 10 violations per episode. With `--init_from` (a run folder,
`{seed}` replaced by the seed) a run starts from that run's networks, so that
the budget tightens a policy that already solves the task; its best policy
within the budget then plays `--test_episodes` episodes seeded apart from
the table's and from training's (on Screw Random, seed 0's first 20 are
also safe_map_shield.py's), read once. One JSON line per run,
also appended to OUTPUT/results.jsonl; then per budget the means over seeds.
"""

import argparse
import json
import pathlib
import shutil
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# Apart from training's, its evaluations' and the table's episode seeds.
FRONTIER_TEST_SEED = 8_000_000


def _violations(row: dict) -> float:
  return sum(row['safety'].values())


def run(args, budget: float | None, seed: int) -> dict:
  from robel_dm.learning import training  # noqa: PLC0415
  from robel_dm.learning.baselines import PLAN  # noqa: PLC0415

  domain, task = args.task.split('/')
  config = training.RunConfig(
    domain=domain,
    task=task,
    seed=seed,
    steps=args.steps,
    eval_every=args.eval_every,
    eval_episodes=1
    if task.endswith('_fixed')
    else PLAN['eval_episodes_random'],
    safety_budget=budget,
    task_kwargs={'action_map': args.action_map},
    init_from=args.init_from.format(seed=seed) if args.init_from else None,
  )
  label = 'none' if budget is None else int(budget)
  warm = '_warm' if args.init_from else ''
  name = f'{task}_{args.action_map}{warm}_budget{label}_{seed}'
  directory = pathlib.Path(args.output) / name
  shutil.rmtree(directory, ignore_errors=True)
  start = time.process_time()
  history = training.train(config, directory, log=lambda line: None)
  last = history[-1]
  safe = [
    row
    for row in history
    if row['success_rate'] >= PLAN['solved']
    and _violations(row) <= PLAN['safe_violations']
  ]
  row = {
    'task': args.task,
    'action_map': args.action_map,
    'budget': budget,
    'seed': seed,
    'init_from': config.init_from,
    'env_steps': last['env_steps'],
    'success': last['success_rate'],
    'violations': last['safety'],
    'safe_success_at': safe[0]['env_steps'] if safe else None,
    'cpu_seconds': round(time.process_time() - start, 1),
  }
  if args.test_episodes:
    row['test'] = _test(args, config, directory)
  return row


def _test(args, config, directory: pathlib.Path) -> dict:
  """The run's best policy (within its budget) on its test episodes."""
  from robel_dm import evaluation, policies  # noqa: PLC0415
  from robel_dm.learning import training  # noqa: PLC0415

  seed = FRONTIER_TEST_SEED + config.seed * 10_000
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      config.domain,
      config.task,
      args.test_episodes,
      policy=policies.load(directory / training.BEST_POLICY),
      seed=seed,
      task_kwargs=config.task_kwargs,
    )
  )
  return {
    'episodes': args.test_episodes,
    'seed': seed,
    'success': results['success_rate'],
    'violations': results['safety'],
  }


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--task', default='dclaw/pose_fixed')
  parser.add_argument('--budgets', default='none,200,50,10')
  parser.add_argument('--seeds', default='0,1,2')
  parser.add_argument('--steps', type=int, default=40_000)
  parser.add_argument('--eval_every', type=int, default=4_000)
  parser.add_argument(
    '--action_map', default='robel', choices=('robel', 'safe')
  )
  parser.add_argument(
    '--init_from',
    default=None,
    help='start each run from this run folder ({seed}: the seed)',
  )
  parser.add_argument(
    '--test_episodes',
    type=int,
    default=0,
    help='then read the best policy on this many test episodes (0: none)',
  )
  parser.add_argument('--output', default=str(ROOT / 'runs/safety_frontier'))
  args = parser.parse_args()
  budgets = [None if b == 'none' else float(b) for b in args.budgets.split(',')]
  output = pathlib.Path(args.output)
  output.mkdir(parents=True, exist_ok=True)
  rows = []
  for budget in budgets:
    for seed in (int(s) for s in args.seeds.split(',')):
      row = run(args, budget, seed)
      rows.append(row)
      print(json.dumps(row), flush=True)
      with open(output / 'results.jsonl', 'a') as file:
        file.write(json.dumps(row) + '\n')
  reading = 'test episodes' if args.test_episodes else 'last evaluation'
  print(f'\n{args.task}, {args.action_map} map: {reading}, seed mean')
  print('budget  success  violations/episode  seeds safe-solved')
  for budget in budgets:
    mine = [r.get('test', r) for r in rows if r['budget'] == budget]
    success = statistics.mean(r['success'] for r in mine)
    violations = statistics.mean(sum(r['violations'].values()) for r in mine)
    safe = sum(
      r['safe_success_at'] is not None for r in rows if r['budget'] == budget
    )
    label = 'none' if budget is None else f'{budget:g}'
    print(
      f'{label:>6}  {success:7.2f}  {violations:18.1f}  {safe} of {len(mine)}'
    )


if __name__ == '__main__':
  main()
