"""Policies for evaluation: built-in, scripted, trained (numpy) and shipped.

A policy maps a `dm_env.TimeStep` to an action. Built in: 'random' (uniform
over the action bounds), 'zero' (the centre of every joint's range) and
'reference' (the task's scripted controller). Trained policies are
`policy.npz` files that `robel_dm.train` writes: the deterministic actor of
a Stable-Baselines3 agent as plain arrays, run here with numpy alone (a
robot's computer needs no torch). `baseline` names the policy shipped for a
task (see docs/baselines.md).

A `policy.npz` holds `weight_<i>` and `bias_<i>` per layer, `activation`
('relu' or 'tanh', between hidden layers), `output` ('tanh': SAC's squashed
mean; 'clip': PPO's mean clipped to [-1, 1]) and `metadata`, a JSON object
with the task it was trained on (domain, task, task_kwargs) and its
observation keys, in the order the flat input concatenates them.
"""

from collections.abc import Callable
import json
import pathlib
from typing import Any

import dm_env
import numpy as np

from robel_dm import assets

Policy = Callable[[dm_env.TimeStep], np.ndarray]

BUILT_IN = ('random', 'zero', 'reference')
BASELINE = 'baseline'
_ACTIVATIONS = {
  'relu': lambda x: np.maximum(x, 0.0),
  'tanh': np.tanh,
}
_OUTPUTS = {
  'tanh': np.tanh,
  'clip': lambda x: np.clip(x, -1.0, 1.0),
}


class PolicyError(ValueError):
  """A policy file that is missing, malformed, or for another task."""


REPLAY = 'replay:'


class ReplayPolicy:
  """The actions of a recording (`robel_dm.recording`), episode by episode.

  Each reset starts the next recorded episode; each step returns the action
  recorded for it. With the recording's seed a simulated episode replays
  exactly.
  """

  def __init__(self, directory: str, domain: str | None, task: str | None):
    from robel_dm import recording  # noqa: PLC0415 (pyarrow)

    episodes = recording.read(directory)
    if not episodes:
      raise PolicyError(f'the recording {directory} has no episodes')
    recorded = (
      episodes[0].metadata.get('domain'),
      episodes[0].metadata.get('task'),
    )
    if domain is not None and recorded != (domain, task):
      raise PolicyError(
        f'the recording {directory} is of {recorded[0]}/{recorded[1]}, not '
        f'{domain}/{task}'
      )
    self._actions = [episode.steps['action'] for episode in episodes]
    self._episode = -1
    self._frame = 0

  def __call__(self, timestep: dm_env.TimeStep) -> np.ndarray:
    if timestep.first():
      self._episode += 1
      self._frame = 0
    if self._episode >= len(self._actions):
      raise PolicyError('the recording has no more episodes to replay')
    actions = self._actions[self._episode]
    self._frame += 1  # Row 0 is the reset; row k holds step k's action.
    if self._frame >= len(actions):
      raise PolicyError(
        f'recorded episode {self._episode} ends after {len(actions) - 1} steps'
      )
    return actions[self._frame]


class NumpyPolicy:
  """A trained deterministic actor, evaluated with numpy.

  Attributes:
    metadata: what it was trained on (domain, task, task_kwargs,
      observation_keys, algo, ...).
  """

  def __init__(
    self,
    weights: list[np.ndarray],
    biases: list[np.ndarray],
    activation: str,
    output: str,
    metadata: dict[str, Any],
  ):
    if activation not in _ACTIVATIONS or output not in _OUTPUTS:
      raise PolicyError(
        f'unknown activation {activation!r} or output {output!r}'
      )
    if not weights or len(weights) != len(biases):
      raise PolicyError(
        'a policy needs as many bias vectors as weight matrices'
      )
    self._weights = [np.asarray(w, np.float64) for w in weights]
    self._biases = [np.asarray(b, np.float64) for b in biases]
    self._activation = _ACTIVATIONS[activation]
    self._output = _OUTPUTS[output]
    self.activation, self.output = activation, output
    self.metadata = dict(metadata)
    self.observation_keys = tuple(metadata.get('observation_keys', ()))

  def __repr__(self) -> str:
    meta = self.metadata
    return (
      f'NumpyPolicy({meta.get("algo", "?")} on '
      f'{meta.get("domain")}/{meta.get("task")})'
    )

  @property
  def input_size(self) -> int:
    return self._weights[0].shape[1]

  def act(self, observation: np.ndarray) -> np.ndarray:
    """The action for a flat observation vector (or a batch of them)."""
    x = np.asarray(observation, np.float64)
    last = len(self._weights) - 1
    for i, (weight, bias) in enumerate(
      zip(self._weights, self._biases, strict=True)
    ):
      x = x @ weight.T + bias
      if i < last:
        x = self._activation(x)
    return self._output(x)

  def __call__(self, timestep: dm_env.TimeStep) -> np.ndarray:
    observation = timestep.observation
    flat = np.concatenate(
      [np.ravel(observation[key]) for key in self.observation_keys]
    )
    return self.act(flat)

  def save(self, path: str | pathlib.Path) -> None:
    # float32, as trained: half the size, and exact for torch's weights.
    arrays = {
      f'weight_{i}': w.astype(np.float32) for i, w in enumerate(self._weights)
    }
    arrays.update(
      {f'bias_{i}': b.astype(np.float32) for i, b in enumerate(self._biases)}
    )
    np.savez(
      path,
      activation=self.activation,
      output=self.output,
      metadata=json.dumps(self.metadata),
      **arrays,
    )

  def check_task(self, domain: str, task: str, task_kwargs=None) -> None:
    """Raises `PolicyError` unless the policy was trained on this task."""
    trained = (self.metadata.get('domain'), self.metadata.get('task'))
    if trained != (domain, task):
      raise PolicyError(
        f'the policy was trained on {trained[0]}/{trained[1]}, not '
        f'{domain}/{task}'
      )
    trained_valve = self.metadata.get('task_kwargs', {}).get('valve')
    valve = (task_kwargs or {}).get('valve')
    if trained_valve != valve:
      raise PolicyError(
        f'the policy was trained with valve {trained_valve or "valve3"}, '
        f'not {valve or "valve3"}'
      )


def load(path: str | pathlib.Path) -> NumpyPolicy:
  """Loads a `policy.npz`.

  Raises:
    PolicyError: if the file is missing or is not a policy.
  """
  path = pathlib.Path(path)
  if not path.is_file():
    raise PolicyError(f'no policy file {path}')
  try:
    with np.load(path, allow_pickle=False) as data:
      layers = sum(1 for name in data.files if name.startswith('weight_'))
      return NumpyPolicy(
        [data[f'weight_{i}'] for i in range(layers)],
        [data[f'bias_{i}'] for i in range(layers)],
        str(data['activation']),
        str(data['output']),
        json.loads(str(data['metadata'])),
      )
  except (OSError, KeyError, ValueError) as error:
    if isinstance(error, PolicyError):
      raise
    raise PolicyError(f'{path} is not a robel_dm policy: {error}') from error


def baseline_path(domain: str, task: str) -> pathlib.Path:
  """The shipped baseline policy of a task.

  Raises:
    PolicyError: if robel_dm ships none for the task.
  """
  directory = assets.baselines_dir()
  path = directory / f'{domain}_{task}.npz'
  if not path.is_file():
    shipped = sorted(p.stem for p in directory.glob('*.npz'))
    raise PolicyError(
      f'no baseline policy for {domain}/{task}; shipped: {shipped} '
      '(see docs/baselines.md)'
    )
  return path


def make_policy(
  name: str,
  env: dm_env.Environment,
  seed: int | None,
  domain: str | None = None,
  task: str | None = None,
  task_kwargs: dict | None = None,
) -> Policy:
  """Builds a policy that maps a timestep to an action for `env`.

  Args:
    name: 'random' (uniform in the action bounds), 'zero' (the centre of
      every joint's range), 'reference' (the task's scripted controller),
      'baseline' (the shipped trained policy of the task), 'replay:DIR'
      (a recording's actions), or the path of a `policy.npz` or a
      Stable-Baselines3 `.zip`.
    env: an environment from `robel_dm.suite.load`.
    seed: seed of the random policy.
    domain: the environment's domain (for trained policies' task check).
    task: the environment's task name.
    task_kwargs: the environment's task arguments (the valve).

  Returns:
    The policy.

  Raises:
    ValueError: for an unknown name, 'reference' on a task that has no
      scripted controller, or a trained policy of another task.
  """
  spec = env.action_spec()
  if name == 'random':
    rng = np.random.default_rng(seed)
    return lambda timestep: rng.uniform(spec.minimum, spec.maximum, spec.shape)
  if name == 'zero':
    zeros = np.zeros(spec.shape, spec.dtype)
    return lambda timestep: zeros
  if name == 'reference':
    task_ = env.task
    try:
      task_.reference_action(env.physics)
    except NotImplementedError as error:
      raise ValueError(
        f'policy "reference" is not available here: {error}'
      ) from error
    return lambda timestep: task_.reference_action(env.physics)
  if name.startswith(REPLAY):
    return ReplayPolicy(name[len(REPLAY) :], domain, task)
  if name == BASELINE:
    name = str(baseline_path(domain, task))
  path = pathlib.Path(name)
  if path.suffix == '.npz' or path.suffix == '.zip':
    if path.suffix == '.zip':
      policy = _load_stable_baselines(path, env)
    else:
      policy = load(path)
    if domain is not None:
      policy.check_task(domain, task, task_kwargs)
    if policy.observation_keys != env.task.agent_observation_keys:
      raise PolicyError(
        f'the policy reads {policy.observation_keys}, the task offers '
        f'{env.task.agent_observation_keys}'
      )
    return policy
  raise ValueError(
    f'unknown policy {name!r}; expected one of {BUILT_IN + (BASELINE,)} or '
    'the path of a policy.npz or Stable-Baselines3 .zip'
  )


def _load_stable_baselines(path: pathlib.Path, env) -> NumpyPolicy:
  """A Stable-Baselines3 checkpoint's actor as a `NumpyPolicy` (needs the
  learn extra); its task is read from the policy.npz beside it if any."""
  if not path.is_file():
    raise PolicyError(f'no policy file {path}')
  from robel_dm import train  # noqa: PLC0415 (torch, only here)

  return train.numpy_policy(train.load_model(path), train.read_metadata(path))
