r"""Robot time to 80% success, per agent, on the simulated robot.

    MUJOCO_GL=egl python benchmarks/robot_time.py --agents=sac,droq \
        --tasks=pose_fixed,stand_fixed --seeds=0,1,2

Each run learns a Fixed task on the in-process virtual bus, the way
`train --device_path=virtual` does: in simulated time, the robot waiting
after every step for the learner to make the updates that step allows
(the pace a learner keeps on a real robot whose control period leaves it
the time; `--updates_per_step` of the agent's own), evaluating the
deterministic actor on the robot every `eval_every` robot steps (one
episode: a Fixed task's episodes are the same) and stopping at the first
evaluation with success >= 0.8; a D'Kitty that fell is stood back on
its start mark by the simulated person of `--reset=manual`. Reported per
run: robot steps and robot seconds (the robot's clock: control periods,
resets and evaluation episodes included) to that evaluation, and the CPU
seconds of the actor's process (the learner's are its own). With
--simulation, each run is also made in simulation (`train`, the same
evaluations and stop), beside it: env steps, wall and CPU seconds to 80%
on this machine. One JSON line per run, also appended to
--output/results.jsonl; then a table of medians per task and agent over
the seeds.
"""

import argparse
import collections
import json
import pathlib
import shutil
import statistics
import sys
import time

import training_speed  # Beside this file.

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# task -> (domain, evaluate every, budget in robot steps).
TASKS = {
  'pose_fixed': ('dclaw', 500, 8_000),
  'stand_fixed': ('dkitty', 500, 8_000),
  'turn_fixed': ('dclaw', 1_000, 24_000),
}
SOLVED = training_speed.SOLVED


def run(algo: str, task: str, seed: int, output: pathlib.Path) -> dict:
  from robel_dm import suite  # noqa: PLC0415
  from robel_dm.learning import robot_training  # noqa: PLC0415

  domain, every, budget = TASKS[task]
  config = training_speed.until_solved(domain, task, algo, seed, every, budget)
  # A person stands a fallen D'Kitty back up (a plain move leaves it
  # fallen, and ROBEL's scripted stand-up does not right it from its back).
  reset = 'manual' if domain == 'dkitty' else None
  options = robot_training.RobotRunOptions(
    suite.RobotOptions('virtual', reset=reset)
  )
  directory = output / f'{task}_{algo}_seed{seed}'
  shutil.rmtree(directory, ignore_errors=True)
  start = time.perf_counter()
  history = robot_training.train_on_robot(
    config, options, directory, log=lambda line: None
  )
  solved = next((r for r in history if r['success_rate'] >= SOLVED), None)
  last = solved or history[-1]
  return {
    'task': task,
    'algo': algo,
    'seed': seed,
    'solved': solved is not None,
    'robot_steps': last['env_steps'],
    'robot_minutes': round(last['robot_seconds'] / 60, 2),
    'cpu_seconds': round(last['cpu_time'], 1),
    'wall_seconds': round(time.perf_counter() - start, 1),
    'budget': budget,
    'eval_every': every,
  }


def simulated(algo: str, task: str, seed: int, output: pathlib.Path) -> dict:
  """The same run in simulation: env steps, wall and CPU seconds to 80%."""
  from robel_dm.learning import training  # noqa: PLC0415

  domain, every, budget = TASKS[task]
  config = training_speed.until_solved(domain, task, algo, seed, every, budget)
  directory = output / f'{task}_{algo}_seed{seed}_simulation'
  shutil.rmtree(directory, ignore_errors=True)
  last = training.train(config, directory, log=lambda line: None)[-1]
  return {
    'sim_solved': last['success_rate'] >= SOLVED,
    'sim_env_steps': last['env_steps'],
    'sim_wall_seconds': round(last['wall_time'], 1),
    'sim_cpu_seconds': round(last['cpu_time'], 1),
  }


def table(results: list[dict]) -> str:
  """Medians over seeds per task and agent (unsolved seeds count as more
  than the budget)."""
  groups = collections.defaultdict(list)
  for row in results:
    groups[(row['task'], row['algo'])].append(row)
  lines = ['task         agent  seeds solved  robot steps  robot min'
           '  sim env steps  sim wall s  sim CPU s']  # fmt: skip
  for (task, algo), rows in sorted(groups.items()):

    def median(key, solved_key='solved', rows=rows):
      values = [r[key] if r[solved_key] else float('inf') for r in rows]
      value = statistics.median_low(values)
      return '> budget' if value == float('inf') else f'{value:,.6g}'

    sim = 'sim_solved' in rows[0]
    lines.append(
      f'{task:12s} {algo:6s} {sum(r["solved"] for r in rows)} of '
      f'{len(rows):<8d} {median("robot_steps"):>11s} '
      f'{median("robot_minutes"):>10s} '
      + (
        f'{median("sim_env_steps", "sim_solved"):>14s} '
        f'{median("sim_wall_seconds", "sim_solved"):>11s} '
        f'{median("sim_cpu_seconds", "sim_solved"):>10s}'
        if sim
        else ''
      )
    )
  return '\n'.join(lines)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--agents', default='sac,droq')
  parser.add_argument('--tasks', default='pose_fixed,stand_fixed')
  parser.add_argument('--seeds', default='0,1,2')
  parser.add_argument('--output', default=str(ROOT / 'runs/robot_time'))
  parser.add_argument('--simulation', action='store_true')
  args = parser.parse_args()
  tasks = args.tasks.split(',')
  for task in tasks:
    if task not in TASKS:
      parser.error(f'--tasks: {task!r} is not one of {sorted(TASKS)}')
  output = pathlib.Path(args.output)
  output.mkdir(parents=True, exist_ok=True)
  results = []
  for task in tasks:
    for seed in (int(s) for s in args.seeds.split(',')):
      for algo in args.agents.split(','):
        result = run(algo, task, seed, output)
        if args.simulation:
          result |= simulated(algo, task, seed, output)
        results.append(result)
        print(json.dumps(result), flush=True)
        with open(output / 'results.jsonl', 'a') as file:
          file.write(json.dumps(result) + '\n')
  print(table(results))


if __name__ == '__main__':
  main()
