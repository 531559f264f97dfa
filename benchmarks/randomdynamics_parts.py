r"""Which part of a RandomDynamics task makes it hard: its changes one by one.

    MUJOCO_GL=egl python benchmarks/randomdynamics_parts.py \
        --task=dkitty/orient [--policy=PATH] [--episodes=50] \
        [--conditions=plain,terrain,dynamics,noise,all,...]

A RandomDynamics task is its Random task plus observation noise on the
robot's joints, physics drawn per episode (joint damping and friction
loss, servo gain, and on some tasks contact friction, the claw mount's
offset and the total mass) and, on the D'Kitty, a random height field
(bumps of 0-5 cm). A policy (by default the Random task's shipped one)
plays the same `--episodes` episodes of the Random task under each
condition: as it is (`plain`), with one change (`noise`, `dynamics`,
`terrain`), with all of them (`all`: the RandomDynamics task), or with one
randomized quantity alone (`damping`, `friction_loss`, `gain`,
`contact_friction`, `mount`, `mass`, those the task randomizes). Printed
per condition: success rate, share of episodes ended by a fall (D'Kitty),
mean score, and ROBEL's safety violations per episode (position, velocity
and current counts summed). The policy acts through the action map it
learned with.
"""

import argparse
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robel_dm import constants, policies, randomization, suite  # noqa: E402
from robel_dm.tasks import base  # noqa: E402

_SEED = 6_000_000  # Apart from training, validation and test episodes.
# A randomized quantity alone: its `DynamicsRanges` fields.
_QUANTITIES = {
  'damping': ('damping', 'damping_shared'),
  'friction_loss': ('friction_loss', 'friction_loss_shared'),
  'gain': ('actuator_kp',),
  'contact_friction': ('geom_friction',),
  'mount': ('mount_offset',),
  'mass': ('total_mass',),
}


def conditions(
  ranges: randomization.DynamicsRanges, terrain: bool
) -> dict[str, dict]:
  """The task arguments of each condition, for a RandomDynamics task that
  randomizes `ranges` (and has `terrain`)."""
  noise = {'observation_noise': constants.OBSERVATION_NOISE_FRACTION}
  every = {
    'dynamics': ranges,
    **noise,
    **({'terrain': True} if terrain else {}),
  }
  table = {'plain': {}, 'noise': noise, 'dynamics': {'dynamics': ranges}}
  if terrain:
    table['terrain'] = {'terrain': True}
  table['all'] = every
  for name, fields in _QUANTITIES.items():
    if getattr(ranges, fields[0]) is not None:
      alone = {field: getattr(ranges, field) for field in fields}
      table[name] = {'dynamics': randomization.DynamicsRanges(**alone)}
  return table


def run(
  domain: str, task: str, policy, task_kwargs: dict, count: int
) -> tuple[float, float, float, float]:
  """Success rate, share of falls, mean score and safety violations per
  episode of `count` episodes."""
  # The policy acts through the action map it learned with.
  task_kwargs = policy.task_kwargs_for(task_kwargs)
  env = suite.load(domain, task, task_kwargs=task_kwargs, seed=_SEED)
  success, fallen, score = [], [], []
  violations = 0
  for _ in range(count):
    timestep = env.reset()
    while not timestep.last():
      timestep = env.step(policy(timestep))
      violations += int(timestep.observation[base.SAFETY].sum())
    success.append(bool(timestep.observation['success']))
    fallen.append(timestep.discount == 0)  # A fall ends with discount 0.
    score.append(float(timestep.observation['score']))
  env.close()
  return np.mean(success), np.mean(fallen), np.mean(score), violations / count


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--task', required=True, help='domain/family')
  parser.add_argument('--policy', default=None)
  parser.add_argument('--episodes', type=int, default=50)
  parser.add_argument('--conditions', default=None)
  args = parser.parse_args()
  domain, family = args.task.split('/')
  randomized = suite.load(domain, f'{family}_random_dynamics').task
  table = conditions(randomized.dynamics, domain == 'dkitty')
  chosen = args.conditions.split(',') if args.conditions else list(table)
  unknown = sorted(set(chosen) - set(table))
  if unknown:
    parser.error(f'unknown conditions {unknown}; known: {list(table)}')
  path = args.policy or policies.baseline_path(domain, f'{family}_random')
  policy = policies.load(path, any_variant=True)
  print(f'{path}: {args.episodes} episodes of {domain}/{family}_random each')
  print('condition         success  fallen  mean score  violations/episode')
  for name in chosen:
    success, fallen, score, violations = run(
      domain, f'{family}_random', policy, table[name], args.episodes
    )
    print(
      f'{name:16}  {success:7.2f}  {fallen:6.2f}  {score:10.3f}  '
      f'{violations:18.1f}',
      flush=True,
    )


if __name__ == '__main__':
  main()
