r"""What makes D'Kitty Walk RandomDynamics hard: its three changes one by one.

    python benchmarks/walk_random_dynamics.py POLICY.npz [POLICY.npz ...] \
        [--episodes=50] [--conditions=plain,terrain,dynamics,noise,all]

Walk RandomDynamics is Walk Random plus three things: a random height
field (bumps of 0-5 cm), randomized physics (joint damping and friction,
actuator gains, contact friction, total mass) and observation noise on the
leg joints. Each policy runs the same `--episodes` fresh episodes (seeded
apart from training and from the baseline table's evaluations) under each
condition: Walk Random as it is ("plain"), with one of the three changes
("terrain", "dynamics", "noise"), or with all of them ("all", which is Walk
RandomDynamics); the randomized physics can also be taken one quantity at
a time ("damping", "friction_loss", "gain", "contact_friction", "mass"):
`--conditions=` picks which. Printed per condition: success rate, share
of episodes ended by a fall, mean distance left to the target at the end,
m, and mean progress toward it, m. Policies trained on another variant
run here on purpose.
"""

import argparse

import randomdynamics_parts  # Beside this file.
import walk_random_targets  # Beside this file.

from robel_dm import policies, randomization

_SEED = 6_000_000
CONDITIONS = randomdynamics_parts.conditions(
  randomization.DKITTY_LOCOMOTION, terrain=True
)


def run(policy: policies.NumpyPolicy, condition: str, count: int) -> dict:
  """`count` episodes of walk_random under `condition`: the means of
  success, fallen, distance left (m) and progress toward the target (m)."""
  result = walk_random_targets.episodes(
    policy, count, _SEED, CONDITIONS[condition]
  )
  return {
    'success': result['success'].mean(),
    'fallen': result['fallen'].mean(),
    'left': result['left'].mean(),
    'progress': result['along'].mean(),
  }


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('policies', nargs='+')
  parser.add_argument('--episodes', type=int, default=50)
  parser.add_argument(
    '--conditions', default='plain,terrain,dynamics,noise,all'
  )
  args = parser.parse_args()
  conditions = args.conditions.split(',')
  unknown = sorted(set(conditions) - set(CONDITIONS))
  if unknown:
    parser.error(f'unknown conditions {unknown}; known: {list(CONDITIONS)}')
  try:
    loaded = [policies.load(path, any_variant=True) for path in args.policies]
  except policies.PolicyError as error:
    parser.error(str(error))
  for path, policy in zip(args.policies, loaded, strict=True):
    print(f'{path}: {args.episodes} episodes of dkitty/walk_random each')
    print('condition         success  fallen  distance left, m  progress, m')
    for condition in conditions:
      result = run(policy, condition, args.episodes)
      print(
        f'{condition:16}  {result["success"]:7.2f}  {result["fallen"]:6.2f}  '
        f'{result["left"]:16.2f}  {result["progress"]:11.2f}',
        flush=True,
      )


if __name__ == '__main__':
  main()
