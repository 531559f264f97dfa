r"""How far a policy turns the valve on D'Claw Turn Fixed, step by step.

    python benchmarks/turn_valve_angles.py POLICY.npz [POLICY.npz ...]

Turn Fixed starts the valve at 0 and sets the goal at 180 degrees; success
is the valve within 0.1 rad (5.7 degrees) of it at the end. A Fixed task's
episodes are all the same episode, so one is the whole answer. For each
policy, prints the valve angle every 4 control steps (0.4 s), the angle
left to the goal at the end, and whether the episode succeeded: a run that
ends unsolved shows where its valve stops. Each policy acts through the
action map it learned with (ROBEL's or the safe one), and a policy of
another Turn variant may be given.
"""

import argparse

import numpy as np

from robel_dm import policies, suite

_SEED = 5_000_000  # Apart from training and the table's evaluations.


def _valve(env) -> float:
  return float(env.physics.named.data.qpos['valve/hinge'][0])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('policies', nargs='+')
  args = parser.parse_args()
  for path in args.policies:
    policy = policies.load(path, any_variant=True)
    env = suite.load(
      'dclaw', 'turn_fixed', seed=_SEED, task_kwargs=policy.task_kwargs_for({})
    )
    timestep = env.reset()
    angles = [_valve(env)]
    while not timestep.last():
      timestep = env.step(policy(timestep))
      angles.append(_valve(env))
    degrees = np.degrees(angles)
    left = abs(degrees[-1] % 360 - 180)  # From the goal, wrapped to +-180.
    print(f'{path}:')
    every = np.round(degrees[::4]).astype(int).tolist()
    print(f'  valve angle every 0.4 s, deg: {every}')
    print(
      f'  left to the goal at the end: {left:.0f} deg; '
      f'success: {bool(timestep.observation["success"])}; action map: '
      f'{policy.action_map}'
    )
    env.close()


if __name__ == '__main__':
  main()
