r"""Wall time to 80% success: the default agent against SB3's SAC defaults.

    MUJOCO_GL=egl python benchmarks/training_speed.py [--tasks=pose_fixed,...]
        [--seeds=0] [--output=runs/training_speed]

Each (task, seed) is trained by both agents at once, one per core (so both
see the same machine), evaluated at the same points, and stopped at the
first evaluation with success >= 0.8 or at the budget. Printed per run:
env steps, training wall seconds (evaluations excluded), whole-run wall
seconds (building the agent, compiling and evaluating included) and CPU
seconds to 80% success; then, per task and seed, the ratio of SB3's time
to the default agent's, in training seconds and in whole-run seconds. If
one agent hits its budget unsolved, the ratio is a bound: a lower bound
(">") if it is SB3's SAC, an upper bound ("<") if it is the default agent.
Runs resume: an interrupted benchmark continues where it stopped (a resumed
run's whole-run seconds count only its last part). The results are kept in
OUTPUT/summary.json; `--summary=OUTPUT/summary.json` prints them again.
"""

import argparse
import concurrent.futures
import json
import multiprocessing
import pathlib
import time

from robel_dm.learning import baselines

ROOT = pathlib.Path(__file__).resolve().parent.parent
AGENTS = ('sac_sb3', 'sac')
# task -> (domain, evaluate every, budget in env steps).
TASKS = {
  'pose_fixed': ('dclaw', 1_000, 30_000),
  'stand_fixed': ('dkitty', 2_000, 60_000),
  'turn_fixed': ('dclaw', 5_000, 120_000),
}
SOLVED = baselines.PLAN['solved']


def until_solved(
  domain: str, task: str, algo: str, seed: int, every: int, budget: int
):
  """A `train` run of a Fixed task that stops at its first evaluation with
  success >= 0.8 (one evaluation episode: every episode is the same)."""
  from robel_dm.learning import training  # noqa: PLC0415

  return training.RunConfig(
    domain=domain,
    task=task,
    algo=algo,
    seed=seed,
    steps=budget,
    eval_every=every,
    eval_episodes=1,
    stop_at_success=SOLVED,
  )


def _run(task: str, seed: int, algo: str, output: str) -> dict:
  start = time.perf_counter()
  from robel_dm.learning import training  # noqa: PLC0415

  domain, every, budget = TASKS[task]
  config = until_solved(domain, task, algo, seed, every, budget)
  directory = pathlib.Path(output) / f'{task}_{algo}_seed{seed}'
  resume = (directory / training.CONFIG).is_file()
  history = (
    training.curves.read_log(directory / training.EVAL_LOG) if resume else []
  )
  if not (history and (history[-1]['success_rate'] >= SOLVED
                       or history[-1]['env_steps'] >= budget)):  # fmt: skip
    history = training.train(config, directory, resume=resume, log=print)
  last = history[-1]
  return {
    'task': task,
    'seed': seed,
    'algo': algo,
    'solved': last['success_rate'] >= SOLVED,
    'env_steps': last['env_steps'],
    'train_seconds': last['wall_time'] - last['eval_time'],
    'cpu_seconds': last['cpu_time'],
    'whole_seconds': time.perf_counter() - start,
  }


def print_results(results: list[dict]) -> None:
  print(
    '\ntask          seed  agent     solved  env steps  train s  whole s'
    '   CPU s'
  )
  for r in results:
    print(
      f'{r["task"]:13s} {r["seed"]:4d}  {r["algo"]:8s}  '
      f'{"yes" if r["solved"] else "no ":6s}  {r["env_steps"]:9d}  '
      f'{r["train_seconds"]:7.0f}  {r["whole_seconds"]:7.0f}  '
      f'{r["cpu_seconds"]:6.0f}'
    )
  print(
    '\nwall time to 80% success, sac_sb3 / sac (same seeds, same run), '
    'training seconds (whole-run seconds):'
  )
  for task, seed in dict.fromkeys((r['task'], r['seed']) for r in results):
    rows = {
      r['algo']: r for r in results if (r['task'], r['seed']) == (task, seed)
    }
    sb3, ours = rows['sac_sb3'], rows['sac']
    if not (sb3['solved'] or ours['solved']):
      print(f'  {task} seed {seed}: neither reached 80% within its budget')
      continue
    # An unsolved run's time is only a bound on its time to 80%.
    if sb3['solved'] and ours['solved']:
      bound, note = '', ''
    elif ours['solved']:
      bound, note = '>', ''
    else:
      bound, note = '<', ' (sac unsolved at its budget)'
    ratio = sb3['train_seconds'] / ours['train_seconds']
    whole = sb3['whole_seconds'] / ours['whole_seconds']
    print(
      f'  {task} seed {seed}: {bound}{ratio:.1f}x ({bound}{whole:.1f}x){note}'
    )


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--tasks', default=','.join(TASKS))
  parser.add_argument('--seeds', default='0')
  parser.add_argument('--output', default=str(ROOT / 'runs/training_speed'))
  parser.add_argument('--summary', help="a finished run's summary.json")
  args = parser.parse_args()
  if args.summary:
    print_results(json.loads(pathlib.Path(args.summary).read_text()))
    return
  results = []
  context = multiprocessing.get_context('spawn')
  with concurrent.futures.ProcessPoolExecutor(2, mp_context=context) as pool:
    for task in args.tasks.split(','):
      for seed in (int(s) for s in args.seeds.split(',')):
        jobs = [
          pool.submit(_run, task, seed, algo, args.output) for algo in AGENTS
        ]
        results.extend(job.result() for job in jobs)
  print_results(results)
  (pathlib.Path(args.output) / 'summary.json').write_text(
    json.dumps(results, indent=1)
  )


if __name__ == '__main__':
  main()
