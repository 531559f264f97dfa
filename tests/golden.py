"""Golden trajectories: every task's seeded episodes, pinned bit for bit.

For each task (and each valve task with the 4-prong valve) three seeded
episodes run under seeded random actions: uniform over the action range,
except that the D'Kitty's second and third episodes draw small actions
around standing (uniform ones topple it within about 15 steps). Every
step's observations (the timestep's and every task observable, enabled or
not), reward, discount, step type and reward terms are recorded; the file
keeps a SHA-256 digest of each quantity's episode array (bit-for-bit
identity) and its sum (to see the size of a difference), and a short digest
of every step's quantities together (to find the first step that differs).
`tests/test_golden.py` compares a fresh run with the file.

Regenerate only after a deliberate change of behaviour, and say why in the
commit:

    MUJOCO_GL=egl python tests/golden.py
"""

import hashlib
import json
import pathlib

import numpy as np

from robel_dm import suite

PATH = pathlib.Path(__file__).with_name('golden_trajectories.json')
EPISODES = 3
# Half-width of the D'Kitty's actions around standing, normalized.
_KITTY_SPREAD = 0.3
_VALVE4 = {'valve': 'valve4'}


def configurations() -> list[tuple[str, str, dict]]:
  """(domain, task, task_kwargs) of every recorded configuration."""
  configs = [(domain, task, {}) for domain, task in suite.ALL_TASKS]
  configs += [
    (domain, task, _VALVE4)
    for domain, task in suite.ALL_TASKS
    if task.startswith(('turn', 'screw'))
  ]
  return configs


def name(domain: str, task: str, task_kwargs: dict) -> str:
  suffix = ''.join(f'/{key}={value}' for key, value in task_kwargs.items())
  return f'{domain}/{task}{suffix}'


def _digest(values: list) -> dict:
  array = np.ascontiguousarray(np.stack([np.asarray(v) for v in values]))
  return {
    'sha256': hashlib.sha256(
      str(array.dtype).encode() + str(array.shape).encode() + array.tobytes()
    ).hexdigest(),
    'sum': float(np.sum(array, dtype=np.float64)),
  }


def _step_digests(steps: dict[str, list]) -> list[str]:
  """Per step, 12 hex digits of the SHA-256 of all its quantities."""
  digests = []
  for index in range(len(steps['reward'])):
    hasher = hashlib.sha256()
    for key in sorted(steps):
      value = np.ascontiguousarray(np.asarray(steps[key][index]))
      hasher.update(key.encode() + str(value.dtype).encode() + value.tobytes())
    digests.append(hasher.hexdigest()[:12])
  return digests


def record(domain: str, task: str, task_kwargs: dict) -> list[dict]:
  """Runs the configuration's episodes; returns per episode the digests."""
  env = suite.load(domain, task, seed=17, task_kwargs=dict(task_kwargs))
  spec = env.action_spec()
  low, high = spec.minimum, spec.maximum
  rng = np.random.default_rng(23)
  observables = env.task.task_observables
  episodes = []
  for episode in range(EPISODES):
    steps: dict[str, list] = {}
    if domain == 'dkitty' and episode > 0:
      standing = env.task.normalize_joint_targets(np.zeros(spec.shape))
      low = np.maximum(standing - _KITTY_SPREAD, spec.minimum)
      high = np.minimum(standing + _KITTY_SPREAD, spec.maximum)

    def add(key, value, steps=steps):
      steps.setdefault(key, []).append(value)

    timestep = env.reset()
    while True:
      add('step_type', int(timestep.step_type))
      add('reward', 0.0 if timestep.reward is None else timestep.reward)
      add('discount', 1.0 if timestep.discount is None else timestep.discount)
      for key, value in timestep.observation.items():
        add(f'observation/{key}', value)
      for key, observable in observables.items():
        add(f'task/{key}', np.asarray(observable(env.physics)))
      for key, value in env.task.reward_terms.items():
        add(f'reward_terms/{key}', value)
      if timestep.last():
        break
      timestep = env.step(rng.uniform(low, high, spec.shape))
    episodes.append(
      {
        'steps': len(steps['reward']),
        'return': float(sum(steps['reward'])),
        'digests': {key: _digest(values) for key, values in steps.items()},
        'step_digests': _step_digests(steps),
      }
    )
  env.close()
  return episodes


def main() -> None:
  golden = {name(*config): record(*config) for config in configurations()}
  PATH.write_text(json.dumps(golden, indent=1, sort_keys=True) + '\n')
  print(f'wrote {len(golden)} configurations to {PATH}')


if __name__ == '__main__':
  main()
