r"""Robot time to 80% on a zoo robot: from a simulation policy vs scratch.

    MUJOCO_GL=egl python benchmarks/fine_tuning.py --task=pose_fixed \
        --robot=claw_sluggish --seeds=0,1,2

Per seed, three runs of `--agent` (default droq, the robot default), all
with what `train --device_path` uses by default (`with_safe_defaults`:
the 'safe' action map and a safety budget of 10 violations per episode):

1. source: the agent learns the Fixed task in simulation (`train`, the
   model's dynamics), evaluated (one episode: a Fixed task's episodes are
   the same) every `--sim_eval_every` env steps and stopping at the first
   evaluation with success >= 0.8 (or at `--sim_budget` env steps);
2. scratch: it learns the task on the zoo robot `--robot` (the in-process
   virtual bus simulating that robot's calibration file, in simulated
   time, the robot waiting after every step for the learner, as in
   benchmarks/robot_time.py), evaluating one episode on the robot every
   `--eval_every` robot steps and stopping at the first evaluation with
   success >= 0.8 or at `--budget` robot steps;
3. from simulation: run 2 with `init_from=` the source run's folder: the
   robot acts with the simulation networks from its first step.

Reported per run: whether it reached 80%, robot steps and robot minutes
(the robot's clock: control periods, resets and evaluation episodes
included) to the solving evaluation, the success of the first evaluation
(robot step 0: for the from-simulation run, the simulation policy on the
robot before any robot learning), ROBEL's score of the first and last
evaluations (averaged over the episode's steps, and at its last step),
the safety violations per episode of
the solving evaluation (of the last one if unsolved), and CPU seconds:
the actor process's to the solving evaluation, and the whole run's (this
process and the learner process, start-up included). For the source run:
env steps and CPU seconds (this process) to 80% in simulation. One JSON
line per run, also appended to OUTPUT/results.jsonl; then a table of
medians per condition over the seeds (unsolved runs count as more than
the budget), and the ratio of the median robot minutes to 80%, scratch /
from simulation, of this invocation's runs.
"""

import argparse
import collections
import json
import pathlib
import resource
import shutil
import statistics
import sys

import training_speed  # Beside this file.

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# task -> (domain, evaluate every, budget), in robot steps.
TASKS = {
  'pose_fixed': ('dclaw', 250, 8_000),
  'turn_fixed': ('dclaw', 1_000, 24_000),
}
SOLVED = training_speed.SOLVED
CONDITIONS = ('scratch', 'from_simulation')


def _cpu_seconds() -> float:
  """CPU seconds of this process and of its finished child processes."""
  total = 0.0
  for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
    usage = resource.getrusage(who)
    total += usage.ru_utime + usage.ru_stime
  return total


def _first_solved(history: list[dict]) -> tuple[bool, dict]:
  """Whether a run reached 80%, and its solving (else last) evaluation."""
  solved = next((r for r in history if r['success_rate'] >= SOLVED), None)
  return solved is not None, solved or history[-1]


def source(args, seed: int, output: pathlib.Path) -> dict:
  """Trains the simulation policy (see the module docstring, run 1).

  Args:
    args: the parsed command line.
    seed: the run's seed.
    output: the benchmark's output directory.

  Returns:
    The run's folder ('folder') and its result.
  """
  from robel_dm.learning import robot_training, training  # noqa: PLC0415

  domain = TASKS[args.task][0]
  config = robot_training.with_safe_defaults(
    training_speed.until_solved(
      domain, args.task, args.agent, seed, args.sim_eval_every, args.sim_budget
    )
  )
  directory = output / f'{args.task}_{args.agent}_seed{seed}_simulation'
  shutil.rmtree(directory, ignore_errors=True)
  start = _cpu_seconds()
  history = training.train(config, directory, log=lambda line: None)
  solved, last = _first_solved(history)
  return {
    'folder': directory,
    'task': args.task,
    'robot': 'simulation',
    'agent': args.agent,
    'seed': seed,
    'condition': 'source',
    'solved': solved,
    'env_steps': last['env_steps'],
    'first_success': history[0]['success_rate'],
    'violations': round(sum(last['safety'].values()), 2),
    'cpu_seconds': round(last['cpu_time'], 1),
    'total_cpu_seconds': round(_cpu_seconds() - start, 1),
    'budget': args.sim_budget,
    'eval_every': args.sim_eval_every,
  }


def on_robot(
  args, seed: int, output: pathlib.Path, init_from: pathlib.Path | None
) -> dict:
  """A run on the zoo robot (see the module docstring, runs 2 and 3).

  Args:
    args: the parsed command line.
    seed: the run's seed.
    output: the benchmark's output directory.
    init_from: the source run's folder (None: from scratch).

  Returns:
    The run's result.
  """
  import dataclasses  # noqa: PLC0415

  from robel_dm import suite, zoo  # noqa: PLC0415
  from robel_dm.learning import robot_training  # noqa: PLC0415

  domain = TASKS[args.task][0]
  config = robot_training.with_safe_defaults(
    training_speed.until_solved(
      domain, args.task, args.agent, seed, args.eval_every, args.budget
    )
  )
  condition = 'scratch' if init_from is None else 'from_simulation'
  if init_from is not None:
    config = dataclasses.replace(config, init_from=str(init_from))
  dynamics = zoo.ROBOTS_DIRECTORY / f'{args.robot}.json'
  options = robot_training.RobotRunOptions(
    suite.RobotOptions('virtual'), dynamics=str(dynamics)
  )
  name = f'{args.task}_{args.robot}_{args.agent}_seed{seed}_{condition}'
  directory = output / name
  shutil.rmtree(directory, ignore_errors=True)
  start = _cpu_seconds()
  history = robot_training.train_on_robot(
    config, options, directory, log=lambda line: None
  )
  solved, last = _first_solved(history)
  return {
    'task': args.task,
    'robot': args.robot,
    'agent': args.agent,
    'seed': seed,
    'condition': condition,
    'solved': solved,
    'robot_steps': last['env_steps'],
    'robot_minutes': round(last['robot_seconds'] / 60, 2),
    'first_success': history[0]['success_rate'],
    # ROBEL's score of the first and last evaluations: how far from the
    # task the run started and got, solved or not.
    'first_score': round(history[0]['mean_score'], 3),
    'last_score': round(history[-1]['mean_score'], 3),
    # The score at the evaluation episode's last step: where the claw
    # ended, however slowly it got there.
    'first_final_score': round(history[0]['mean_final_score'], 3),
    'last_final_score': round(history[-1]['mean_final_score'], 3),
    'violations': round(sum(last['safety'].values()), 2),
    'violations_by_kind': {k: round(v, 2) for k, v in last['safety'].items()},
    'cpu_seconds': round(last['cpu_time'], 1),
    'total_cpu_seconds': round(_cpu_seconds() - start, 1),
    'budget': args.budget,
    'eval_every': args.eval_every,
  }


def _median(rows: list[dict], key: str) -> float:
  """The median of `key` over `rows`, an unsolved run's as infinity."""
  values = [r[key] if r['solved'] else float('inf') for r in rows]
  return statistics.median_low(values)


def _shown(value: float) -> str:
  return '> budget' if value == float('inf') else f'{value:,.6g}'


def table(results: list[dict]) -> str:
  """Medians per condition over the seeds, and the robot-minutes ratio."""
  groups = collections.defaultdict(list)
  for row in results:
    groups[row['condition']].append(row)
  lines = [
    'condition        seeds solved  steps to 80%  robot min  first success'
    '  violations  CPU s (actor)  CPU s (all)'
  ]
  for condition in ('source', *CONDITIONS):
    rows = groups.get(condition)
    if not rows:
      continue
    steps = 'env_steps' if condition == 'source' else 'robot_steps'
    minutes = '-'
    if condition != 'source':
      minutes = _shown(_median(rows, 'robot_minutes'))
    first = statistics.median_low(r['first_success'] for r in rows)
    violations = statistics.median_low(r['violations'] for r in rows)
    lines.append(
      f'{condition:16s} {sum(r["solved"] for r in rows)} of {len(rows):<6d} '
      f'{_shown(_median(rows, steps)):>12s} {minutes:>10s} {first:>14.2f} '
      f'{violations:>11.2f} '
      f'{statistics.median_low(r["cpu_seconds"] for r in rows):>14.1f} '
      f'{statistics.median_low(r["total_cpu_seconds"] for r in rows):>12.1f}'
    )
  lines.append(_ratio(groups))
  return '\n'.join(lines)


def _ratio(groups: dict[str, list[dict]]) -> str:
  """The median robot minutes to 80%, scratch / from simulation."""
  if not all(groups.get(c) for c in CONDITIONS):
    return 'ratio: needs both conditions'
  scratch, warm = (_median(groups[c], 'robot_minutes') for c in CONDITIONS)
  label = 'median robot minutes to 80%, scratch / from simulation:'
  if warm == float('inf'):
    return f'{label} undefined (from simulation unsolved within the budget)'
  if scratch == float('inf'):
    budget = groups['scratch'][0]['budget']
    return f'{label} > budget ({budget} robot steps) / {warm:g} min'
  if warm == 0:
    return f'{label} inf (from simulation solved at robot step 0)'
  return f'{label} {scratch:g} / {warm:g} = {scratch / warm:.1f}x'


def _arguments() -> argparse.Namespace:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--task', default='pose_fixed', choices=sorted(TASKS))
  parser.add_argument('--robot', default='claw_sluggish')
  parser.add_argument('--seeds', default='0,1,2')
  parser.add_argument('--agent', default='droq')
  parser.add_argument('--budget', type=int, help='robot steps')
  parser.add_argument('--eval_every', type=int, help='robot steps')
  parser.add_argument('--sim_budget', type=int, help='simulation env steps')
  parser.add_argument('--sim_eval_every', type=int, help='simulation steps')
  parser.add_argument('--output', default=str(ROOT / 'runs/fine_tuning'))
  args = parser.parse_args()
  _, every, budget = TASKS[args.task]
  _, sim_every, sim_budget = training_speed.TASKS[args.task]
  args.budget = args.budget or budget
  args.eval_every = args.eval_every or every
  args.sim_budget = args.sim_budget or sim_budget
  args.sim_eval_every = args.sim_eval_every or sim_every
  return args


def main() -> None:
  args = _arguments()
  output = pathlib.Path(args.output)
  output.mkdir(parents=True, exist_ok=True)
  results = []

  def report(result: dict) -> None:
    results.append(result)
    print(json.dumps(result), flush=True)
    with open(output / 'results.jsonl', 'a') as file:
      file.write(json.dumps(result) + '\n')

  for seed in (int(s) for s in args.seeds.split(',')):
    result = source(args, seed, output)
    folder = result.pop('folder')
    report(result)
    report(on_robot(args, seed, output, None))
    report(on_robot(args, seed, output, folder))
  print(table(results))


if __name__ == '__main__':
  main()
