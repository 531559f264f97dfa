r"""Which turns a policy makes on D'Kitty Orient Random, and which succeed.

    python benchmarks/orient_random_turns.py POLICY.npz [POLICY.npz ...] \
        [--episodes=100]

Orient Random starts the robot at a heading in +-60 degrees and puts the
target 120-240 degrees around, so the turn it needs is 60-180 degrees, to
the left or to the right; Orient Fixed always needs 180 (either way). For
each policy, on the same `--episodes` fresh episodes (seeded apart from
training and from the baseline table's evaluations), prints per band of the
needed turn (signed: + left, counter-clockwise) the success rate, the mean
angle left to the target at the end, and how far the robot turned on
average in the needed direction. Policies trained on Orient Fixed run here
on purpose (another variant of their task).
"""

import argparse

import numpy as np

from robel_dm import policies, suite

_SEED = 3_000_000
# Needed turn bands, degrees (+: to the left).
_BANDS = ((-180, -120), (-120, -60), (60, 120), (120, 180.01))


def _signed_angle(a: np.ndarray, b: np.ndarray) -> float:
  """From direction a to direction b, rad (+: counter-clockwise)."""
  return float(np.arctan2(a[0] * b[1] - a[1] * b[0], a @ b))


def _episodes(path: str, count: int) -> dict[str, np.ndarray]:
  policy = policies.load(path, any_variant=True)
  # The policy acts through the action map it learned with.
  env = suite.load(
    'dkitty', 'orient_random', task_kwargs=policy.task_kwargs_for(None),
    seed=_SEED,
  )  # fmt: skip
  rows = []
  for _ in range(count):
    timestep = env.reset()
    obs = timestep.observation
    needed = _signed_angle(obs['current_facing'], obs['desired_facing'])
    yaw = [float(obs['root_euler'][2])]
    while not timestep.last():
      timestep = env.step(policy(timestep))
      yaw.append(float(timestep.observation['root_euler'][2]))
    obs = timestep.observation
    turned = float(np.unwrap(yaw)[-1] - yaw[0])
    left = abs(_signed_angle(obs['current_facing'], obs['desired_facing']))
    rows.append((needed, turned, left, bool(obs['success'])))
  env.close()
  needed, turned, left, success = (np.array(c) for c in zip(*rows, strict=True))
  return {'needed': needed, 'turned': turned, 'left': left, 'success': success}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('policies', nargs='+')
  parser.add_argument('--episodes', type=int, default=100)
  args = parser.parse_args()
  for path in args.policies:
    result = _episodes(path, args.episodes)
    needed = np.degrees(result['needed'])
    print(f'{path}: {args.episodes} episodes of dkitty/orient_random')
    print('needed turn, deg   share  success  angle left, deg  '
          'turned in the needed direction, deg')  # fmt: skip
    for low, high in _BANDS:
      band = (needed >= low) & (needed < high)
      if not band.any():
        continue
      along = np.degrees(result['turned'][band]) * np.sign(needed[band])
      print(
        f'{low:6.0f} .. {min(high, 180):4.0f}   {band.mean():5.2f}  '
        f'{result["success"][band].mean():7.2f}  '
        f'{np.degrees(result["left"][band]).mean():15.1f}  {along.mean():8.1f}'
      )
    print(f'all                1.00  {result["success"].mean():7.2f}  '
          f'{np.degrees(result["left"]).mean():15.1f}')  # fmt: skip


if __name__ == '__main__':
  main()
