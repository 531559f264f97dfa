r"""Where Stand Random's episodes start, and from which starts anything stands.

    MUJOCO_GL=egl python benchmarks/stand_random_starts.py [--episodes=200] \
        [--policy=POLICY.npz]

For `--episodes` initial states of dkitty/stand_random (one environment per
controller, both seeded alike, so both see the same states), records how
upright the torso is after ROBEL's settling (upright = cosine of the torso's
tilt) and runs two controllers from it: the task's scripted ramp to standing
(`reference`) and the shipped Stand Fixed policy (`baseline` of stand_fixed,
evaluated here on the other variant on purpose), and with `--policy` a
policy file too. Prints the success rate of each, and of the better of the
two, per band of initial uprightness, and the share of starts in each band.
"""

import argparse

import numpy as np

from robel_dm import policies, suite

_SEED = 1_000_000
# Initial uprightness bands: on its back or side, tilted, about level.
_BANDS = ((-1.01, 0.0), (0.0, 0.5), (0.5, 0.9), (0.9, 1.01))


def _episodes(driver: str, count: int) -> tuple[np.ndarray, np.ndarray]:
  """(upright after settling, success at the last step) per episode."""
  if driver == 'reference':
    env = suite.load('dkitty', 'stand_random', seed=_SEED)
    policy = policies.make_policy('reference', env, _SEED)
  else:  # A policy file, or the Fixed task's shipped one.
    path = (
      policies.baseline_path('dkitty', 'stand_fixed')
      if driver == 'fixed'
      else driver
    )
    policy = policies.load(path, any_variant=True)
    # The policy acts through the action map it learned with.
    env = suite.load(
      'dkitty', 'stand_random', task_kwargs=policy.task_kwargs_for(None),
      seed=_SEED,
    )  # fmt: skip
  starts, success = [], []
  for _ in range(count):
    timestep = env.reset()
    starts.append(float(timestep.observation['upright'][0]))
    while not timestep.last():
      timestep = env.step(policy(timestep))
    success.append(bool(timestep.observation['success']))
  return np.array(starts), np.array(success)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--episodes', type=int, default=200)
  parser.add_argument(
    '--policy', help='also a policy.npz (e.g. one trained on Stand Random)'
  )
  args = parser.parse_args()
  starts, reference = _episodes('reference', args.episodes)
  same_starts, fixed = _episodes('fixed', args.episodes)
  if not np.array_equal(starts, same_starts):
    raise RuntimeError('the two controllers saw different initial states')
  success = {'reference': reference, 'fixed policy': fixed}
  success['either'] = success['reference'] | success['fixed policy']
  if args.policy:
    policy_starts, success['policy'] = _episodes(args.policy, args.episodes)
    if not np.array_equal(starts, policy_starts):
      raise RuntimeError('the policy saw different initial states')
  print(f'{args.episodes} initial states of dkitty/stand_random')
  print('initial upright   share   ' + '  '.join(f'{k:>12s}' for k in success))
  for low, high in _BANDS:
    band = (starts >= low) & (starts < high)
    rates = '  '.join(
      f'{value[band].mean() if band.any() else float("nan"):12.2f}'
      for value in success.values()
    )
    print(
      f'{max(low, -1):5.1f} .. {min(high, 1):4.1f}   {band.mean():5.2f}   '
      f'{rates}'
    )
  overall = '  '.join(f'{value.mean():12.2f}' for value in success.values())
  print(f'all               1.00   {overall}')


if __name__ == '__main__':
  main()
