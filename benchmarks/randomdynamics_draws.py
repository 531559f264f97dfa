r"""On which draws of a RandomDynamics task its policies fail.

    MUJOCO_GL=egl python benchmarks/randomdynamics_draws.py \
        --task=dkitty/orient_random_dynamics --policies=A.npz,B.npz \
        [--episodes=200] [--output=episodes.jsonl]

Every policy plays the same `--episodes` seeded episodes of the task
(seeds from 7,000,000: apart from the baseline table's training,
validation and test episodes and from randomdynamics_parts.py's). Each
episode keeps its success, whether it ended early (a D'Kitty's fall) and
what was drawn for it at reset: the randomized physics
(`Task.dynamics_draws`, each scaled to [-1, 1] over ROBEL's range; a
per-joint quantity by its mean over the joints), on the D'Kitty the
terrain under the torso (the mean of its 7 x 7 cells and their spread,
highest less lowest, scaled the same way over 0-5 cm), and ROBEL's score
at reset, which the task's own draws set (on Orient 1 - the angle to
turn / pi, on Walk minus the distance to the target).

Printed: per policy, success over all episodes, and success in the third
of the episodes with the lowest draws of each quantity, the middle third
and the highest third (episodes in brackets; the episodes are the same
for every policy). A quantity whose low or high third holds most failures
of every policy is where the task is hardest. Last, the episodes that no
policy solves, against their number if the policies failed independently
(the product of their failure rates): an episode some policy solves is
not made infeasible by its draws. With `--output`, one JSON line per
policy and episode.

Also printed: each policy's failed episodes, how many of them ended early
and the median final score (ROBEL's score at the last step) of the rest:
how near a policy that did not fall ended.
"""

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robel_dm import policies, suite  # noqa: E402
from robel_dm.evaluation import episodes  # noqa: E402

_SEED = 7_000_000
# Quantities drawn per component (named), not per joint.
_COMPONENTS = {
  'geom_friction': ('slide', 'spin', 'roll'),
  'mount_offset': ('x', 'y', 'z'),
}
_THIRDS = ('low', 'middle', 'high')


def drawn(env) -> dict[str, float]:
  """What was drawn for the episode just reset: the physics and the
  terrain, each in [-1, 1], and ROBEL's score at reset."""
  quantities = {
    'score_at_reset': float(env.task.task_observables['score'](env.physics))
  }
  for name, values in env.task.dynamics_draws.items():
    if name in _COMPONENTS and values.size == len(_COMPONENTS[name]):
      for part, value in zip(_COMPONENTS[name], values, strict=True):
        quantities[f'{name}.{part}'] = float(value)
    else:
      quantities[name] = float(np.mean(values))
  arena = env.task.arena
  if getattr(arena, 'has_terrain', False):
    torso = env.physics.bind(env.task.root_joint).qpos[:2]
    patch = arena.terrain_around(torso)
    quantities['terrain.mean'] = float(patch.mean())
    quantities['terrain.spread'] = float(patch.max() - patch.min())
  return quantities


def play(domain: str, task: str, path: str, count: int) -> list[dict]:
  """The episodes of the policy at `path`: success, early end, draws."""
  policy = policies.load(path, any_variant=True)
  env = suite.load(domain, task, task_kwargs=policy.task_kwargs_for({}))
  rows = []
  for index in range(count):
    draws = {}

    def on_step(draws=draws):
      if not draws:  # The first call follows the reset.
        draws.update(drawn(env))

    record, steps, _ = episodes.run_episode(
      env, policy, _SEED + index, on_step=on_step
    )
    rows.append({
      'policy': path,
      'episode_seed': _SEED + index,
      'success': record['success'],
      'ended_early': steps < env.task.episode_steps,
      'score': record['mean_score'],
      'final_score': record['final_score'],
      'draws': draws,
    })  # fmt: skip
  env.close()
  return rows


def thirds(rows: list[dict], quantity: str) -> list[str]:
  """Each episode's third of the episodes by its draw of `quantity`
  (ties in rank order)."""
  values = [row['draws'][quantity] for row in rows]
  ranks = np.argsort(np.argsort(values, kind='stable'), kind='stable')
  return [_THIRDS[3 * int(rank) // len(rows)] for rank in ranks]


def table(results: dict[str, list[dict]]) -> str:
  """Success per policy, overall and by third of each drawn quantity."""
  names = list(results)
  lines = [f'policy {i}: {name}' for i, name in enumerate(names)]
  heading = ''.join(f'{"policy " + str(i):>16s}' for i in range(len(names)))
  lines.append(f'{"drawn quantity":28s}{heading}')
  lines.append(
    f'{"all episodes":28s}' + ''.join(_cell(rows) for rows in results.values())
  )
  quantities = list(next(iter(results.values()))[0]['draws'])
  for quantity in quantities:
    # The episodes, and so their draws, are the same for every policy.
    parts = thirds(next(iter(results.values())), quantity)
    for part in _THIRDS:
      cells = ''.join(
        _cell([r for r, p in zip(rows, parts, strict=True) if p == part])
        for rows in results.values()
      )
      lines.append(f'{quantity + " " + part:28s}{cells}')
  lines.append(_failures(results))
  lines.append(_unsolved(results))
  return '\n'.join(lines)


def _failures(results: dict[str, list[dict]]) -> str:
  """Per policy: its failed episodes, those ended early, and the median
  final score of the others (how near they ended)."""
  cells = []
  for i, rows in enumerate(results.values()):
    failed = [r for r in rows if not r['success']]
    early = sum(r['ended_early'] for r in failed)
    last = [r['final_score'] for r in failed if not r['ended_early']]
    median = f'{np.median(last):.3f}' if last else '-'
    cells.append(f'policy {i} {len(failed)} ({early} early, {median})')
  return 'failed (of them ended early, median final score of the rest): ' + (
    '; '.join(cells)
  )


def _unsolved(results: dict[str, list[dict]]) -> str:
  """The episodes no policy solves, against independent failures."""
  successes = np.array(
    [[row['success'] for row in rows] for rows in results.values()]
  )
  count = successes.shape[1]
  unsolved = int(np.sum(~successes.any(axis=0)))
  independent = count * np.prod(1.0 - successes.mean(axis=1))
  return (
    f'solved by no policy: {unsolved} of {count} episodes '
    f'(if the policies failed independently: {independent:.1f})'
  )


def _cell(rows: list[dict]) -> str:
  if not rows:
    return f'{"-":>16s}'
  success = np.mean([r['success'] for r in rows])
  return f'{success:10.2f} ({len(rows):3d})'


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--task', required=True, help='domain/task')
  parser.add_argument('--policies', required=True, help='comma-separated')
  parser.add_argument('--episodes', type=int, default=200)
  parser.add_argument('--output', default=None, help='a JSONL file')
  args = parser.parse_args()
  domain, task = args.task.split('/')
  if args.episodes < 1:
    parser.error(f'--episodes must be at least 1: {args.episodes}')
  if not suite.load(domain, task).task.dynamics_draws:
    parser.error(f'{args.task} randomizes no physics')
  results = {
    path: play(domain, task, path, args.episodes)
    for path in args.policies.split(',')
  }
  first = [row['draws'] for row in next(iter(results.values()))]
  for path, rows in results.items():
    if [row['draws'] for row in rows] != first:
      sys.exit(f'{path}: its episodes drew other physics than the first')
  if args.output:
    with open(args.output, 'w') as file:
      for rows in results.values():
        file.writelines(json.dumps(row) + '\n' for row in rows)
  print(f'{args.task}: {args.episodes} episodes per policy')
  print(table(results))


if __name__ == '__main__':
  main()
