"""Policies for evaluation: built-in, scripted, trained (numpy) and shipped.

A policy maps a `dm_env.TimeStep` to an action. Built in: 'random' (uniform
over the action bounds), 'zero' (the centre of every joint's range) and
'reference' (the task's scripted controller). Trained policies are
`policy.npz` files that `robel-train` writes: the deterministic actor of
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
import re
from typing import Any

import dm_env
import numpy as np

from robel_dm import assets, npz_files, registry, suite
from robel_dm.tasks import base

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

  def __init__(
    self,
    directory: str,
    domain: str | None,
    task: str | None,
    task_kwargs: dict | None = None,
    seed: int | None = None,
    *,
    episodes: int | None = None,
    check_seed: bool = False,
  ):
    """Reads the recording and checks it against the replay.

    Args:
      directory: the recording directory.
      domain: the replay's domain (None: no check of the task).
      task: the replay's task.
      task_kwargs: the replay's task arguments.
      seed: the replay's seed: its episode i is reset with `seed + i`, as
        `evaluate` resets them (None: fresh seeds).
      episodes: how many episodes will be replayed (None: any number).
      check_seed: refuse a seed other than the recorded one.

    Raises:
      PolicyError: naming what differs (recorded and requested value)
        where the recording says: the task (domain, task, task_kwargs),
        the seed (if `check_seed`), or too few episodes.
    """
    from robel_dm import recording  # noqa: PLC0415 (pyarrow)

    recorded = recording.read(directory)
    if not recorded:
      raise PolicyError(f'the recording {directory} has no episodes')
    if episodes is not None and episodes > len(recorded):
      raise PolicyError(
        f'the recording {directory} has {len(recorded)} episodes, not '
        f'{episodes}'
      )
    for i, episode in enumerate(recorded[:episodes]):
      if domain is not None:
        _check_task(directory, episode.metadata, domain, task, task_kwargs)
      if check_seed:
        _check_seed(directory, episode.metadata, i, seed)
      if episodes is not None and not episode.metadata.get('complete', True):
        # Found now, not when the replay runs out of actions mid-episode.
        raise PolicyError(
          f'episode {i} of the recording {directory} was cut short after '
          f'{len(episode) - 1} steps; replay the {i} before it '
          f'(--episodes={i})'
        )
    self._actions = [episode.steps['action'] for episode in recorded]
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


def _as_json(value) -> Any:
  """`value` as a JSON round trip gives it back (tuples as lists)."""
  return json.loads(json.dumps(value or {}, sort_keys=True, default=repr))


def _check_task(directory, metadata: dict, domain, task, task_kwargs) -> None:
  """Raises PolicyError if a recorded episode's metadata names another
  domain, task or task_kwargs (what it does not name passes)."""
  said = metadata.get('domain', domain), metadata.get('task', task)
  if said != (domain, task):
    raise PolicyError(
      f'the recording {directory} is of {said[0]}/{said[1]}, not '
      f'{domain}/{task}'
    )
  kwargs = _as_json(metadata.get('task_kwargs', task_kwargs))
  if kwargs != _as_json(task_kwargs):
    raise PolicyError(
      f'the recording {directory} was made with task_kwargs '
      f'{json.dumps(kwargs)}, not {json.dumps(_as_json(task_kwargs))}'
    )


def _check_seed(directory, metadata: dict, index: int, seed) -> None:
  """Raises PolicyError unless recorded episode `index` was reset as a
  replay from `seed` resets it (with `seed + index`, as `evaluate` does);
  passes where the recording does not say."""
  session = metadata.get('seed')  # The seed evaluate was given.
  reset = metadata.get('episode_seed')  # Its reset's (recent recordings).
  if reset is None:  # Not said: an older recording's session seed.
    if session is None or session == seed:
      return
  elif reset == (None if seed is None else seed + index):
    return
  elif session is None or session + index != reset:  # Appended sessions.
    raise PolicyError(
      f'episode {index} of the recording {directory} was reset with seed '
      f'{reset}, not {seed} + {index} (--allow_other_seed replays it anyway)'
    )
  raise PolicyError(
    f'the recording {directory} was made with seed {session}, not {seed} '
    '(--allow_other_seed replays it anyway)'
  )


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
    self._weights = [
      _real_array(w, f'weight_{i}') for i, w in enumerate(weights)
    ]
    self._biases = [_real_array(b, f'bias_{i}') for i, b in enumerate(biases)]
    _check_layers(self._weights, self._biases)
    self._activation = _ACTIVATIONS[activation]
    self._output = _OUTPUTS[output]
    self.activation, self.output = activation, output
    self.metadata = dict(metadata)
    self.observation_keys = tuple(metadata.get('observation_keys', ()))
    # Whether `check_task` accepts other variants of the task's family.
    self.any_variant = False

  def __repr__(self) -> str:
    # Recordings store this: it names the trained run, seed included.
    meta = self.metadata
    return (
      f'NumpyPolicy({meta.get("algo", "?")} seed {meta.get("seed", "?")} '
      f'on {meta.get("domain")}/{meta.get("task")})'
    )

  @property
  def input_size(self) -> int:
    return self._weights[0].shape[1]

  @property
  def output_size(self) -> int:
    return self._weights[-1].shape[0]

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
    """Raises `PolicyError` unless the policy was trained on this task
    (or, with `any_variant` set, on another variant of its family: a
    generalization study, e.g. a Fixed task's policy on the Random one)."""
    trained = (self.metadata.get('domain'), str(self.metadata.get('task')))
    if self.any_variant:
      same = trained[0] == domain and (
        trained[1].split('_')[0] == task.split('_')[0]
      )
    else:
      same = trained == (domain, task)
    if not same:
      hint = '' if self.any_variant else ' (see --allow_other_variant)'
      raise PolicyError(
        f'the policy was trained on {trained[0]}/{trained[1]}, not '
        f'{domain}/{task}{hint}'
      )
    # The policy's own action map and privileged observation are adopted
    # where the task arguments name none; its valve must be the task's.
    for option, theirs, ours in base.interface_differences(
      self.metadata.get('task_kwargs'), self.task_kwargs_for(task_kwargs)
    ):
      hint = '' if option == 'valve' else f' (leave {option} out)'
      raise PolicyError(
        f'the policy was trained with {option} {theirs}, not {ours}{hint}'
      )

  @property
  def action_map(self) -> str:
    """The action map the policy learned through ('robel' or 'safe')."""
    return self.metadata.get('task_kwargs', {}).get('action_map', 'robel')

  @property
  def privileged(self) -> bool:
    """Whether the policy reads the task's privileged observation (what
    only a simulation knows): a ceiling, not a policy for a robot."""
    return bool(self.metadata.get('task_kwargs', {}).get('privileged'))

  def task_kwargs_for(
    self, task_kwargs: dict | None, log=None, doing: str = 'running'
  ) -> dict:
    """`task_kwargs` with the policy's action map and privileged
    observation where they name none: a policy acts through the map it
    learned with, on the observation it learned from. `log`, if given, is
    told each option adopted ('... : {doing} with it')."""
    given = dict(task_kwargs or {})
    task_kwargs = dict(given)
    if self.action_map != 'robel':
      task_kwargs.setdefault('action_map', self.action_map)
    if self.privileged:
      task_kwargs.setdefault(
        'privileged', self.metadata['task_kwargs']['privileged']
      )
    adopted = [option for option in task_kwargs if option not in given]
    for option in adopted if log is not None else ():
      log(
        f'the policy learned with task option {option}='
        f'{task_kwargs[option]}: {doing} with it'
      )
    return task_kwargs


def _real_array(value, name: str) -> np.ndarray:
  array = np.asarray(value)
  if array.dtype.kind not in 'fiu':
    raise PolicyError(f'{name} holds {array.dtype} values, not numbers')
  array = array.astype(np.float64)
  if not np.all(np.isfinite(array)):
    raise PolicyError(f'{name} holds non-finite values')
  return array


def _check_layers(weights: list[np.ndarray], biases: list[np.ndarray]) -> None:
  """Raises `PolicyError` unless the layers chain: weight_i is (out, in),
  bias_i is (out,), and each layer takes the previous layer's output."""
  for i, (weight, bias) in enumerate(zip(weights, biases, strict=True)):
    if weight.ndim != 2 or 0 in weight.shape:
      raise PolicyError(f'weight_{i} has shape {weight.shape}, not (out, in)')
    if bias.shape != weight.shape[:1]:
      raise PolicyError(
        f'bias_{i} has shape {bias.shape}, weight_{i} needs '
        f'({weight.shape[0]},)'
      )
    if i and weight.shape[1] != weights[i - 1].shape[0]:
      raise PolicyError(
        f'weight_{i} takes {weight.shape[1]} inputs, layer {i - 1} gives '
        f'{weights[i - 1].shape[0]}'
      )


_LAYER = re.compile(r'(weight|bias)_(0|[1-9][0-9]*)')
_FIELDS = ('activation', 'output', 'metadata')
# The most a policy's arrays may hold in all, checked from their headers
# before any is read (the shipped policies hold less than 1 MiB).
MAX_ARRAY_BYTES = 256 * 2**20


def _read_arrays(path: pathlib.Path) -> dict[str, np.ndarray]:
  """The arrays of a .npz file (raises `PolicyError` without the path; an
  unreadable file's OSError is named by `load`)."""
  try:
    return npz_files.read_arrays(path, MAX_ARRAY_BYTES)
  except npz_files.ArchiveError as error:
    raise PolicyError(str(error)) from error


def _from_arrays(arrays: dict[str, np.ndarray]) -> NumpyPolicy:
  """A policy from a policy.npz's arrays (raises `PolicyError` without the
  path)."""
  missing = [name for name in _FIELDS if name not in arrays]
  if missing:
    raise PolicyError(f'no {", ".join(missing)} array')
  layers = {'weight': set(), 'bias': set()}
  unexpected = []
  for name in arrays:
    match = _LAYER.fullmatch(name)
    if match:
      layers[match[1]].add(int(match[2]))
    elif name not in _FIELDS:
      unexpected.append(name)
  if unexpected:
    raise PolicyError(f'unexpected arrays {sorted(unexpected)}')
  count = len(layers['weight'])
  expected = set(range(count))
  if not count or not layers['weight'] == layers['bias'] == expected:
    raise PolicyError(
      'the layers must be weight_0.., bias_0.. with one bias per weight; '
      f'found weights {sorted(layers["weight"])}, biases '
      f'{sorted(layers["bias"])}'
    )
  try:
    metadata = json.loads(str(arrays['metadata']))
  except ValueError as error:
    raise PolicyError(f'metadata is not JSON ({error})') from None
  if not isinstance(metadata, dict):
    raise PolicyError('metadata is not a JSON object')
  keys = metadata.get('observation_keys')
  if not (
    isinstance(keys, list) and keys and all(isinstance(k, str) for k in keys)
  ):
    raise PolicyError('metadata names no observation_keys')
  if not isinstance(metadata.get('task_kwargs', {}), dict):
    raise PolicyError('metadata task_kwargs is not a JSON object')
  return NumpyPolicy(
    [arrays[f'weight_{i}'] for i in range(count)],
    [arrays[f'bias_{i}'] for i in range(count)],
    str(arrays['activation']),
    str(arrays['output']),
    metadata,
  )


def load(path: str | pathlib.Path, any_variant: bool = False) -> NumpyPolicy:
  """Loads a `policy.npz`, checking that it is whole and well formed;
  `any_variant` lets it run on other variants of its task.

  Raises:
    PolicyError: if the file is missing, unreadable or not a policy (one
      line naming the file and what is wrong).
  """
  path = pathlib.Path(path)
  if not path.is_file():
    raise PolicyError(f'no policy file {path}')
  try:
    policy = _from_arrays(_read_arrays(path))
  except OSError as error:  # Unreadable: permissions, I/O errors.
    raise PolicyError(
      f'cannot read {path}: {error.strerror or error}'
    ) from None
  except PolicyError as error:
    raise PolicyError(f'{path} is not a robel_dm policy: {error}') from None
  policy.any_variant = any_variant
  return policy


def _check_sizes(
  policy: NumpyPolicy,
  where: str,
  keys: tuple[str, ...],
  observation_size: int,
  action_size: int,
) -> None:
  """Raises `PolicyError` unless the policy reads `keys` (in order) and maps
  `observation_size` values to `action_size` actions."""
  if policy.observation_keys != tuple(keys):
    raise PolicyError(
      f'the policy reads {policy.observation_keys}, {where} offers {keys}'
    )
  if policy.input_size != observation_size:
    raise PolicyError(
      f'the policy takes {policy.input_size} observation values, {where} '
      f'gives {observation_size}'
    )
  if policy.output_size != action_size:
    raise PolicyError(
      f'the policy gives {policy.output_size} actions, {where} takes '
      f'{action_size}'
    )


def _task_sizes(domain: str, task: str, task_kwargs) -> tuple:
  """The agent's observation keys, observation size and action size of a
  task, from a task instance (no environment, no robot)."""
  try:
    instance = registry.DOMAINS[domain][task](**(task_kwargs or {}))
  except TypeError as error:
    if 'keyword argument' not in str(error):
      raise
    raise ValueError(f'bad task_kwargs for {domain}/{task}: {error}') from None
  return (
    instance.agent_observation_keys,
    instance.agent_observation_size,
    len(instance.robot.actuators),
  )


def check_file(
  name: str | Any,
  domain: str,
  task: str,
  task_kwargs: dict | None = None,
  any_variant: bool = False,
) -> NumpyPolicy | None:
  """Checks a policy named by path (or 'baseline') before any environment
  is built: the file is there and whole, and fits the task (trained on it,
  its observation keys and sizes, its action size).

  Args:
    name: the policy as `make_policy` takes it (other values pass).
    domain: the task's domain.
    task: the task's name.
    task_kwargs: the task's arguments.
    any_variant: accept a policy of another variant of the task's family.

  Returns:
    The loaded policy of a policy.npz, else None.

  Raises:
    PolicyError: naming the file and what is wrong.
    ValueError: for an unknown policy name or bad task arguments.
  """
  tasks = suite.TASKS_BY_DOMAIN.get(domain, ())
  if not isinstance(name, str) or task not in tasks:
    return None  # Not a name, or suite.load names the unknown task.
  if name in BUILT_IN or name.startswith(REPLAY):
    return None
  path = baseline_path(domain, task) if name == BASELINE else pathlib.Path(name)
  if path.suffix != '.npz':
    raise _unknown_policy(name, domain, task)
  if not path.is_file():
    raise PolicyError(f'no policy file {path}')
  policy = load(path, any_variant)
  try:
    policy.check_task(domain, task, task_kwargs)
    keys, observation_size, action_size = _task_sizes(
      domain, task, policy.task_kwargs_for(task_kwargs)
    )
    _check_sizes(
      policy, f'{domain}/{task}', keys, observation_size, action_size
    )
  except PolicyError as error:
    raise PolicyError(f'{path}: {error}') from None
  return policy


def _unknown_policy(
  name: str, domain: str | None = None, task: str | None = None
) -> ValueError:
  if name.endswith('.zip'):  # A Stable-Baselines3 model or checkpoint.
    return ValueError(
      f'{name} is a Stable-Baselines3 .zip: convert it to a policy.npz first '
      f'with robel-convert --model={name} --algo=ALGO '
      f'--domain={domain or "D"} --task={task or "T"} --output=policy.npz, '
      'ALGO being sac, tqc or ppo (train writes a policy.npz beside its '
      'checkpoint.zip)'
    )
  return ValueError(
    f'unknown policy {name!r}; expected one of {BUILT_IN + (BASELINE,)} or '
    'the path of a policy.npz'
  )


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
      (a recording's actions), or the path of a `policy.npz`.
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
    return ReplayPolicy(name[len(REPLAY) :], domain, task, task_kwargs)
  if name == BASELINE:
    name = str(baseline_path(domain, task))
  path = pathlib.Path(name)
  if path.suffix == '.npz':
    policy = load(path)
    if domain is not None:
      policy.check_task(domain, task, task_kwargs)
    if policy.action_map != env.task.action_map:
      raise PolicyError(
        f'{path} learned through the {policy.action_map} action map; this '
        f'task acts through the {env.task.action_map} one: build it with '
        f"task_kwargs action_map='{policy.action_map}'"
      )
    keys = env.task.agent_observation_keys
    observations = env.observation_spec()
    _check_sizes(
      policy,
      'the task',
      keys,
      sum(int(np.prod(observations[key].shape)) for key in keys),
      int(np.prod(spec.shape)),
    )
    return policy
  raise _unknown_policy(name, domain, task)
