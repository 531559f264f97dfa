r"""Screw Random's success by goal speed: how fast can a policy turn the valve?

    MUJOCO_GL=egl python benchmarks/screw_random_speeds.py POLICY.npz \
        [--episodes=100] [--first_seed=1000000]

Runs a trained Screw policy (its task arguments, e.g. extra observation
keys, come from its metadata) on `--episodes` episodes of dclaw/screw_random
from seed `--first_seed` on, and prints, per band and direction of the
episode's goal velocity v (ROBEL draws v uniformly in [-0.75, 0.75] rad/s),
the share of episodes in the band, the success rate
(mean |angle error| below 0.2 rad), the mean |angle error|, and the valve's
mean speed over the episode (net turn over 8 s, in the goal's direction),
for goals turning each way. The default first seed, 1,000,000, is where
`train`'s evaluation seeds start; a seed of 7,000,000 or more is apart
from every seed the table uses.
"""

import argparse

import numpy as np

from robel_dm import policies, suite

_SEED = 1_000_000
_BANDS = ((0.0, 0.25), (0.25, 0.5), (0.5, 0.75))


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('policy')
  parser.add_argument('--episodes', type=int, default=100)
  parser.add_argument('--first_seed', type=int, default=_SEED)
  args = parser.parse_args()
  policy = policies.load(args.policy, any_variant=True)
  task_kwargs = policy.metadata.get('task_kwargs', {})
  velocities, success, errors, valve_speeds = [], [], [], []
  for episode in range(args.episodes):
    env = suite.load(
      'dclaw',
      'screw_random',
      task_kwargs=task_kwargs,
      seed=args.first_seed + episode,
    )
    timestep = env.reset()
    task = env.task
    hinge = env.physics.bind(task.valve.hinge)
    start_angle = float(hinge.qpos[0])
    velocity = task.goal_velocity
    distances = []
    while not timestep.last():
      timestep = env.step(policy(timestep))
      distances.append(abs(float(timestep.observation['target_error'][0])))
    duration = env.physics.data.time
    turned = float(hinge.qpos[0]) - start_angle
    velocities.append(velocity)
    valve_speeds.append(turned / duration * np.sign(velocity or 1.0))
    errors.append(np.mean(distances))
    success.append(bool(timestep.observation['success']))
    env.close()
  velocities, success = np.array(velocities), np.array(success)
  speeds = np.abs(velocities)
  errors, valve_speeds = np.array(errors), np.array(valve_speeds)
  print(
    f'{args.episodes} episodes of dclaw/screw_random from seed '
    f'{args.first_seed}, {args.policy}'
  )
  print('goal v rad/s      share  success  mean |error| rad  valve speed rad/s')
  for sign in (1, -1):
    for low, high in _BANDS:
      band = (speeds >= low) & (speeds < high) & (np.sign(velocities) == sign)
      if not band.any():
        continue
      label = f'{sign * low:+5.2f} .. {sign * high:+5.2f}'
      print(
        f'{label}    {band.mean():5.2f}  {success[band].mean():7.2f}  '
        f'{errors[band].mean():16.3f}  {valve_speeds[band].mean():17.3f}'
      )
  print(f'all               1.00  {success.mean():7.2f}  {errors.mean():16.3f}')


if __name__ == '__main__':
  main()
