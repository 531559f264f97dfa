"""Simple policies for evaluation: random, zero and scripted reference."""

from collections.abc import Callable

import dm_env
import numpy as np

Policy = Callable[[dm_env.TimeStep], np.ndarray]

POLICIES = ('random', 'zero', 'reference')


def make_policy(name: str, env: dm_env.Environment, seed: int | None) -> Policy:
  """Builds a policy that maps a timestep to an action for `env`.

  Args:
    name: 'random' (uniform in the action bounds), 'zero' (the centre of
      every joint's range) or 'reference' (the task's scripted controller).
    env: an environment from `robel_dm.suite.load`.
    seed: seed of the random policy.

  Returns:
    The policy.

  Raises:
    ValueError: for an unknown name, or 'reference' on a task that has no
      scripted controller.
  """
  spec = env.action_spec()
  if name == 'random':
    rng = np.random.default_rng(seed)
    return lambda timestep: rng.uniform(spec.minimum, spec.maximum, spec.shape)
  if name == 'zero':
    zeros = np.zeros(spec.shape, spec.dtype)
    return lambda timestep: zeros
  if name == 'reference':
    task = env.task
    try:
      task.reference_action(env.physics)
    except NotImplementedError as error:
      raise ValueError(
        f'policy "reference" is not available here: {error}'
      ) from error
    return lambda timestep: task.reference_action(env.physics)
  raise ValueError(f'unknown policy {name!r}; expected one of {POLICIES}')
