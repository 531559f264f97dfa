r"""Which targets a policy reaches on D'Kitty Walk Random.

    python benchmarks/walk_random_targets.py POLICY.npz [POLICY.npz ...] \
        [--episodes=100]

Walk Random puts the target 1-2 m away at -60..60 degrees from straight
ahead; Walk Fixed always 2 m straight ahead. For each policy, on the same
`--episodes` fresh episodes (seeded apart from training and from the
baseline table's evaluations), prints per band of the target's angle
(+: to the left) the success rate, the mean distance left at the end, m,
and how far the robot got along the direction to its target, m. Policies
trained on Walk Fixed run here on purpose (another variant of their task).
"""

import argparse

import numpy as np

from robel_dm import policies, suite

_SEED = 4_000_000
# Target angle bands, degrees (+: to the left of straight ahead).
_BANDS = ((-60, -20), (-20, 20), (20, 60.01))


def episodes(
  policy: policies.NumpyPolicy, count: int, seed: int, task_kwargs=None
) -> dict[str, np.ndarray]:
  """`count` episodes of walk_random (with `task_kwargs`), per episode: the
  target's angle from straight ahead and distance at the start, the
  distance left at the end, progress along the direction to the target,
  success, and whether a fall ended it."""
  # The policy acts through the action map it learned with.
  task_kwargs = policy.task_kwargs_for(task_kwargs)
  env = suite.load('dkitty', 'walk_random', task_kwargs=task_kwargs, seed=seed)
  rows = []
  for _ in range(count):
    timestep = env.reset()
    error = np.asarray(timestep.observation['target_error'], float)
    start = np.asarray(timestep.observation['root_pos'][:2], float)
    # Headings count from +y: the angle of the target from straight ahead.
    angle = float(np.arctan2(-error[0], error[1]))
    while not timestep.last():
      timestep = env.step(policy(timestep))
    obs = timestep.observation
    moved = np.asarray(obs['root_pos'][:2], float) - start
    along = float(moved @ error / np.linalg.norm(error))
    left = float(np.linalg.norm(obs['target_error']))
    fallen = timestep.discount == 0  # A fall ends an episode, discount 0.
    rows.append(
      (angle, np.linalg.norm(error), left, along, obs['success'], fallen)
    )
  env.close()
  names = ('angle', 'distance', 'left', 'along', 'success', 'fallen')
  columns = (np.array(c, float) for c in zip(*rows, strict=True))
  return dict(zip(names, columns, strict=True))


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('policies', nargs='+')
  parser.add_argument('--episodes', type=int, default=100)
  args = parser.parse_args()
  for path in args.policies:
    policy = policies.load(path, any_variant=True)
    result = episodes(policy, args.episodes, _SEED)
    angle = np.degrees(result['angle'])
    print(f'{path}: {args.episodes} episodes of dkitty/walk_random')
    print('target angle, deg  share  success  distance left, m  '
          'progress toward it, m')  # fmt: skip
    for low, high in _BANDS:
      band = (angle >= low) & (angle < high)
      if band.any():
        print(
          f'{low:5.0f} .. {min(high, 60):3.0f}    {band.mean():5.2f}  '
          f'{result["success"][band].mean():7.2f}  '
          f'{result["left"][band].mean():16.2f}  '
          f'{result["along"][band].mean():8.2f}'
        )
    print(
      f'all               1.00  {result["success"].mean():7.2f}  '
      f'{result["left"].mean():16.2f}  {result["along"].mean():8.2f}'
    )


if __name__ == '__main__':
  main()
