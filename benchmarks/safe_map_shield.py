r"""The safe action map as a shield for policies that learned without it.

    MUJOCO_GL=egl python benchmarks/safe_map_shield.py [--episodes=20] \
        [--tasks=dclaw/pose_random,...]

Each task's shipped policy (`policies/`) plays the same `--episodes`
episodes twice: through ROBEL's action map, which it learned with, and
through the safe one (`task_kwargs={'action_map': 'safe'}`: targets kept 1
degree inside the safety counters' bounds and moved at most 0.9 times
their speed limit), which it never saw. Printed per task: the policy's
agent and seed, and success and safety violations per episode (all kinds
summed) either way. `evaluate` refuses to run a policy through a map it
did not learn with; this benchmark does it on purpose, on a copy of the
policy whose metadata names the safe map.
"""

import argparse
import copy
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robel_dm import evaluation, policies, suite  # noqa: E402

_SEED = 8_000_000  # Apart from training, validation and test episodes.


def run(domain: str, task: str, episodes: int) -> str:
  policy = policies.load(policies.baseline_path(domain, task))
  row = [f'{domain}/{task}', policy.metadata['algo'], policy.metadata['seed']]
  for action_map in ('robel', 'safe'):
    shielded = copy.copy(policy)
    shielded.metadata = copy.deepcopy(policy.metadata)
    task_kwargs = {**policy.metadata['task_kwargs'], 'action_map': action_map}
    shielded.metadata['task_kwargs'] = task_kwargs
    results = evaluation.evaluate(
      evaluation.EvalConfig(
        domain, task, episodes, policy=shielded, seed=_SEED,
        task_kwargs=task_kwargs,
      )
    )  # fmt: skip
    row += [results['success_rate'], sum(results['safety'].values())]
  return '{:28s} {:10s} {:4d} {:8.2f} {:10.1f} {:8.2f} {:10.1f}'.format(*row)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--episodes', type=int, default=20)
  parser.add_argument(
    '--tasks',
    default=','.join(f'{d}/{t}' for d, t in suite.RANDOM),
    help='comma-separated domain/task',
  )
  args = parser.parse_args()
  print(
    f'{"task":28s} {"agent":10s} {"seed":>4s} {"robel":>8s} {"violations":>10s}'
    f' {"safe":>8s} {"violations":>10s}'
  )
  for name in args.tasks.split(','):
    print(run(*name.split('/'), args.episodes), flush=True)


if __name__ == '__main__':
  main()
