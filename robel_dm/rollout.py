"""One episode of a policy, and what it measured: the loop that every
evaluation (serial, worker processes, Ray tasks) runs."""

import time
from typing import Any

import numpy as np

from robel_dm import policies
from robel_dm.tasks import base


def run_episode(
  env, act: policies.Policy, episode_seed: int | None, on_step=None
) -> tuple[dict[str, Any], int, float]:
  """Runs one episode from a seeded reset.

  Args:
    env: the environment.
    act: the policy.
    episode_seed: the reset's seed; None continues the random state.
    on_step: called after the reset and after every step (e.g. to add a
      video frame); its time is not counted as step time.

  Returns:
    Its record, its number of steps and the seconds spent in `env.step`.
  """
  if episode_seed is not None:
    env.random_state.seed(episode_seed)
  timestep = env.reset()
  if on_step is not None:
    on_step()
  episode_return, scores = 0.0, []
  safety = np.zeros(len(base.SAFETY_FIELDS), dtype=np.int64)
  step_seconds = 0.0
  while not timestep.last():
    action = act(timestep)
    start = time.perf_counter()
    timestep = env.step(action)
    step_seconds += time.perf_counter() - start
    if on_step is not None:
      on_step()
    episode_return += timestep.reward
    scores.append(float(timestep.observation[base.SCORE]))
    safety += timestep.observation[base.SAFETY]
  record = {
    'seed': episode_seed,
    'return': episode_return,
    'mean_score': float(np.mean(scores)),
    'final_score': scores[-1],
    'success': bool(timestep.observation[base.SUCCESS]),
    'steps': len(scores),
    'safety': dict(zip(base.SAFETY_FIELDS, safety.tolist(), strict=True)),
  }
  return record, len(scores), step_seconds
