"""robel_dm tasks as Gymnasium environments, under ROBEL's names.

    import gymnasium as gym
    env = gym.make('robel_dm:robel_dm/DClawTurnFixed-v0')
    obs, info = env.reset(seed=0)
    action = env.action_space.sample()
    obs, reward, terminated, truncated, info = env.step(action)

(`import robel_dm.learning.gym` registers the ids too; then the
`robel_dm:` prefix can be left out.)

The observation is ROBEL's flat agent vector (float32, in the order of the
task's `agent_observation_keys`); the action a float32 Box in [-1, 1]. The
signals never enter the observation: `info` holds `score`, `success`,
`safety` (violations this step per counter) and `reward_terms`. A D'Kitty
fall is `terminated`; the end of the time limit is `truncated`.

`step` checks the action as the robel_dm environment does (shape, real
numbers, finite, in [-1, 1] unless the task clips) and raises its
ValueError before anything reaches the environment; stepping before the
first `reset` or after an episode ended raises `ResetNeededError`.

Ids: ROBEL's (`DClawPoseFixed-v0` ... `DKittyWalkRandomDynamics-v0`) and,
for Turn and Screw with the 4-prong valve, `DClawTurnFixedValve4-v0` etc.
`gym.make(id, seed=..., task_kwargs=..., robot=suite.RobotOptions(...),
...)` passes `suite.load`'s arguments through.
"""

from typing import Any

import dm_env
import numpy as np

from robel_dm import robots, suite
from robel_dm.learning import extra
from robel_dm.tasks import base

try:
  import gymnasium
  from gymnasium import spaces
except ImportError as error:  # The optional learn extra.
  raise extra.missing(error) from error

NAMESPACE = 'robel_dm'
_VARIANT_NAMES = {
  'fixed': 'Fixed',
  'random': 'Random',
  'random_dynamics': 'RandomDynamics',
}
_VALVE4 = {'valve': 'valve4'}


def env_name(domain: str, task: str, valve4: bool = False) -> str:
  """ROBEL's name of a task: ('dclaw', 'turn_fixed') -> 'DClawTurnFixed'."""
  family, variant = task.split('_', 1)
  name = (
    robots.ROBOTS[domain].gym_prefix
    + family.capitalize()
    + _VARIANT_NAMES[variant]
  )
  return name + ('Valve4' if valve4 else '')


def env_ids() -> dict[str, tuple[str, str, dict]]:
  """Every registered id -> (domain, task, task_kwargs)."""
  ids = {}
  for domain, task in suite.ALL_TASKS:
    ids[f'{NAMESPACE}/{env_name(domain, task)}-v0'] = (domain, task, {})
    if task.startswith(('turn', 'screw')):
      ids[f'{NAMESPACE}/{env_name(domain, task, valve4=True)}-v0'] = (
        domain,
        task,
        dict(_VALVE4),
      )
  return ids


class ResetNeededError(gymnasium.error.ResetNeeded, RuntimeError):
  """`step` before the first `reset` or after the episode ended.

  Both Gymnasium's error for this (the one `gymnasium.make`'s order check
  raises before the first reset) and a RuntimeError (what the adapter
  raised before the first reset in earlier versions).
  """


class RobelEnv(gymnasium.Env):
  """A robel_dm task with Gymnasium's API (see the module docstring)."""

  metadata = {'render_modes': ['rgb_array']}

  def __init__(
    self,
    domain: str,
    task: str,
    *,
    task_kwargs: dict[str, Any] | None = None,
    id_task_kwargs: dict[str, Any] | None = None,
    render_mode: str | None = None,
    render_size: tuple[int, int] = (240, 320),
    **load_kwargs,
  ):
    """Loads the task.

    Args:
      domain: 'dclaw' or 'dkitty'.
      task: a task of the domain, e.g. 'turn_fixed'.
      task_kwargs: the task's arguments.
      id_task_kwargs: arguments the registered id implies (the 4-prong
        valve); `task_kwargs` are added to them.
      render_mode: None or 'rgb_array'.
      render_size: (height, width) of rendered frames, pixels.
      **load_kwargs: further `suite.load` arguments (`seed`, `time_limit`,
        `robot`, `dynamics`, `environment_kwargs`).
    """
    if render_mode not in (None, 'rgb_array'):
      raise ValueError(f'render_mode must be None or rgb_array: {render_mode}')
    self.domain, self.task_name = domain, task
    self.task_kwargs = {**(id_task_kwargs or {}), **(task_kwargs or {})}
    self._env = suite.load(
      domain, task, task_kwargs=self.task_kwargs, **load_kwargs
    )
    self.render_mode = render_mode
    self.metadata = {
      **self.metadata,
      'render_fps': round(1 / self._env.control_timestep()),
    }
    self._render_size = render_size
    task_ = self._env.task
    self._keys = task_.agent_observation_keys
    spec = self._env.observation_spec()
    sizes = {key: int(np.prod(spec[key].shape)) for key in self._keys}
    size = sum(sizes.values())
    # The privileged observation (`TaskOptions.privileged`) comes last.
    self.privileged_size = sizes.get(base.PRIVILEGED, 0)
    self.observation_space = spaces.Box(
      -np.inf, np.inf, shape=(size,), dtype=np.float32
    )
    action_spec = self._env.action_spec()
    self.action_space = spaces.Box(
      -1.0, 1.0, shape=action_spec.shape, dtype=np.float32
    )
    self._timestep: dm_env.TimeStep | None = None
    self._needs_reset = True

  @property
  def robel_env(self) -> dm_env.Environment:
    """The underlying robel_dm environment."""
    return self._env

  @property
  def observation_keys(self) -> tuple[str, ...]:
    """The observations in the agent vector, in order."""
    return self._keys

  def _observation(self, timestep: dm_env.TimeStep) -> np.ndarray:
    observation = timestep.observation
    return np.concatenate(
      [np.ravel(observation[key]) for key in self._keys]
    ).astype(np.float32)

  def _info(self, timestep: dm_env.TimeStep) -> dict[str, Any]:
    observation = timestep.observation
    safety = observation[base.SAFETY]
    return {
      'score': float(observation[base.SCORE]),
      'success': bool(observation[base.SUCCESS]),
      'safety': dict(zip(base.SAFETY_FIELDS, safety.tolist(), strict=True)),
      'reward_terms': self._env.task.reward_terms,
    }

  def reset(self, *, seed: int | None = None, options=None):
    """Starts an episode; a seed reseeds the task's random state."""
    del options
    super().reset(seed=seed)
    if seed is not None:
      self._env.random_state.seed(seed)
    self._timestep = self._env.reset()
    self._needs_reset = False
    return self._observation(self._timestep), self._info(self._timestep)

  def step(self, action):
    """Applies an action for one control step.

    Args:
      action: one normalized joint target per actuator, real numbers in
        [-1, 1] (any array-like the robel_dm environment accepts).

    Returns:
      (observation, reward, terminated, truncated, info).

    Raises:
      ResetNeededError: before the first `reset` or after the episode ended.
      ValueError: for an action the robel_dm environment rejects (wrong
        shape, not real numbers, not finite, outside [-1, 1]); nothing is
        sent to the environment.
    """
    if self._needs_reset:
      raise ResetNeededError(
        'call reset() before step()'
        if self._timestep is None
        else 'the episode ended: call reset() before step()'
      )
    # The task's own check, so that exactly what the environment rejects is
    # rejected, with its message, before the environment sees the action
    # (a plain float conversion would let complex numbers, numeric strings
    # and objects through).
    action = self._env.task.validated_action(action)
    timestep = self._env.step(action)
    self._timestep = timestep
    last = timestep.last()
    self._needs_reset = last
    terminated = last and timestep.discount == 0.0
    truncated = last and not terminated
    return (
      self._observation(timestep),
      float(timestep.reward),
      terminated,
      truncated,
      self._info(timestep),
    )

  def render(self):
    if self.render_mode != 'rgb_array':
      return None
    height, width = self._render_size
    return self._env.physics.render(height=height, width=width)

  def set_randomization_scale(self, scale: float) -> None:
    """See `RobelTask.set_randomization_scale`."""
    self._env.task.set_randomization_scale(scale)

  @property
  def randomization_scale(self) -> float | None:
    """See `RobelTask.randomization_scale`."""
    return self._env.task.randomization_scale

  def close(self):
    self._env.close()


def register_environments() -> None:
  """Registers every task's id with Gymnasium (idempotent)."""
  registry = gymnasium.envs.registry
  for env_id, (domain, task, task_kwargs) in env_ids().items():
    if env_id in registry:
      continue
    gymnasium.register(
      id=env_id,
      entry_point='robel_dm.learning.gym:RobelEnv',
      kwargs={'domain': domain, 'task': task, 'id_task_kwargs': task_kwargs},
    )


register_environments()
