r"""A Stable-Baselines3 model as a `policy.npz` that `evaluate` runs.

`convert` reads and checks a model, `save` writes the policy (the
`robel-convert` command is `robel_dm.commands.convert`). The algo is `sac`
(stable_baselines3.SAC), `tqc` (sb3_contrib.TQC) or `ppo`
(stable_baselines3.PPO); the model must have been trained on the task's
Gymnasium environment (`gymnasium.make('robel_dm:robel_dm/<Name>-v0')`:
the flat agent observation, actions in [-1, 1]). Before anything is
written the conversion checks that the file holds a model of the algo
(read from the archive, before anything in it is unpickled), that its
observation and action spaces are the task's, and that the numpy policy
gives the model's deterministic actions (`model.predict(obs,
deterministic=True)`) on the task's reset observations and random ones,
within `TOLERANCE`. Any failure is a `ConvertError`, one line.
"""

import dataclasses
import importlib
import json
import os
import pathlib
import tempfile
from typing import Any
import zipfile

import numpy as np

from robel_dm import policies
from robel_dm.learning import agents, gym

# Observations the actions are compared on: the first RESETS are reset
# states (one seed each), the rest random.
CHECKED_OBSERVATIONS = 100
RESETS = 10
# float32 torch against float64 numpy: well above their rounding, far below
# any difference that would change what a robot does.
TOLERANCE = 1e-5
_SEED = 0


class ConvertError(ValueError):
  """A model that cannot be converted (one line, naming what is wrong)."""


@dataclasses.dataclass(frozen=True)
class _Algo:
  library: str  # The package and class that load it.
  cls: str
  policies: str  # The module of its policy class, as the .zip names it.


ALGOS = {
  'sac': _Algo('stable_baselines3', 'SAC', 'stable_baselines3.sac.policies'),
  'tqc': _Algo('sb3_contrib', 'TQC', 'sb3_contrib.tqc.policies'),
  # PPO's ActorCriticPolicy (A2C's and TRPO's too: their actors are alike).
  'ppo': _Algo('stable_baselines3', 'PPO', 'stable_baselines3.common.policies'),
}


def _one_line(error: BaseException) -> str:
  message = ' '.join(str(error).split())
  name = type(error).__name__
  return f'{name}: {message}' if message else name


def _check_archive(path: pathlib.Path, algo: str) -> None:
  """Raises ConvertError unless `path` is an SB3 .zip of `algo`'s policy,
  from its `data` JSON (no pickle is loaded)."""
  try:
    with zipfile.ZipFile(path) as archive:
      data = json.loads(archive.read('data'))
    module = data['policy_class']['__module__']
  except zipfile.BadZipFile:
    raise ConvertError(f'{path} is not a zip archive') from None
  except (KeyError, TypeError, ValueError) as error:
    raise ConvertError(
      f'{path} is not a Stable-Baselines3 model ({_one_line(error)})'
    ) from None
  if module == ALGOS[algo].policies:
    return
  held = [name for name, a in ALGOS.items() if a.policies == module]
  if held:
    raise ConvertError(
      f'{path} holds a {held[0].upper()} model, not {algo.upper()}: give '
      f'--algo={held[0]}'
    )
  raise ConvertError(
    f'{path} holds a model with policies from {module}; convert takes '
    f'{", ".join(ALGOS)} (stable_baselines3 SAC, sb3_contrib TQC, '
    'stable_baselines3 PPO)'
  )


def _load_model(path: pathlib.Path, algo: str):
  """The model, on the CPU, with torch on one thread."""
  agents.single_thread()
  spec = ALGOS[algo]
  cls = getattr(importlib.import_module(spec.library), spec.cls)
  try:
    return cls.load(str(path), device='cpu')
  except Exception as error:  # noqa: BLE001 (a damaged file raises anything)
    raise ConvertError(
      f'cannot load {path} as a {spec.library} {spec.cls} model: '
      f'{_one_line(error)}'
    ) from None


def _describe(space, what: str) -> str:
  """'27 observation values' for a flat Box, else the space itself."""
  shape = getattr(space, 'shape', None)
  if isinstance(shape, tuple) and len(shape) == 1:
    return f'{shape[0]} {what} values'
  return f'{what}s {space}'


def _check_spaces(model, env: gym.RobelEnv, where: str) -> None:
  """Raises ConvertError unless the model takes the task's flat observation
  and gives its actions in [-1, 1]."""
  observations, actions = model.observation_space, model.action_space
  size = env.observation_space.shape[0]
  if getattr(observations, 'shape', None) != (size,):
    raise ConvertError(
      f'the model takes {_describe(observations, "observation")}, {where} '
      f'gives {size} ({", ".join(env.observation_keys)})'
    )
  count = env.action_space.shape[0]
  if getattr(actions, 'shape', None) != (count,):
    raise ConvertError(
      f'the model gives {_describe(actions, "action")}, {where} takes {count}'
    )
  if not (np.all(actions.low == -1.0) and np.all(actions.high == 1.0)):
    raise ConvertError(
      f'the model gives actions in [{actions.low.min()}, '
      f'{actions.high.max()}], {where} takes them in [-1, 1]'
    )


def _observations(env: gym.RobelEnv) -> np.ndarray:
  """The observations actions are compared on: the task's reset states
  (seeds 0..RESETS-1), then standard normal vectors (seeded)."""
  resets = [env.reset(seed=seed)[0] for seed in range(RESETS)]
  rng = np.random.default_rng(_SEED)
  random = rng.standard_normal(
    (CHECKED_OBSERVATIONS - RESETS, env.observation_space.shape[0])
  )
  return np.concatenate([np.stack(resets), random]).astype(np.float32)


def _compare(model, policy: policies.NumpyPolicy, observations) -> float:
  """The largest difference between the model's deterministic actions and
  the policy's (raises ConvertError above TOLERANCE)."""
  expected, _ = model.predict(observations, deterministic=True)
  actual = policy.act(observations)
  difference = float(np.max(np.abs(actual - expected)))
  if not difference <= TOLERANCE:  # NaN fails too.
    raise ConvertError(
      f'the numpy policy differs from the model by up to {difference:.3g} '
      f'(tolerance {TOLERANCE:g}) on {len(observations)} observations: '
      'not converted'
    )
  return difference


def convert(
  model_path: str | pathlib.Path,
  algo: str,
  domain: str,
  task: str,
  task_kwargs: dict[str, Any] | None = None,
) -> policies.NumpyPolicy:
  """The deterministic actor of a saved SB3 model, checked, for numpy.

  Args:
    model_path: the model's .zip (what `model.save` writes).
    algo: 'sac', 'tqc' or 'ppo'.
    domain: the domain the model was trained on.
    task: its task.
    task_kwargs: its task arguments (the valve).

  Returns:
    The policy, its metadata naming the task and the model it came from.

  Raises:
    ConvertError: naming what is wrong: an unknown algo, a missing file or
      one that is not a model of `algo`, spaces that are not the task's,
      an actor numpy cannot run, or actions that differ from the model's.
    ValueError: for an unknown task or bad task arguments.
  """
  if algo not in ALGOS:
    raise ConvertError(f'--algo must be one of {", ".join(ALGOS)}: {algo!r}')
  path = pathlib.Path(model_path)
  if not path.is_file():
    raise ConvertError(f'no model file {path}')
  _check_archive(path, algo)
  task_kwargs = dict(task_kwargs or {})
  env = gym.RobelEnv(domain, task, task_kwargs=task_kwargs)
  try:
    model = _load_model(path, algo)
    try:
      _check_spaces(model, env, f'{domain}/{task}')
    except ConvertError as error:
      raise ConvertError(f'{path}: {error}') from None
    metadata = {
      'domain': domain,
      'task': task,
      'task_kwargs': task_kwargs,
      'observation_keys': list(env.observation_keys),
      'algo': algo,
      'seed': model.seed,
      'converted_from': path.name,
    }
    try:
      policy = agents.numpy_policy(model, metadata)
    except ValueError as error:
      raise ConvertError(
        f'{path}: numpy cannot run its actor: {error}'
      ) from None
    observations = _observations(env)
  finally:
    env.close()
  policy.metadata['checked'] = {
    'observations': len(observations),
    'max_difference': _compare(model, policy, observations),
  }
  return policy


def save(policy: policies.NumpyPolicy, output: str | pathlib.Path) -> None:
  """Writes the policy in one step: an interrupted write leaves no file."""
  output = pathlib.Path(output)
  handle, temporary = tempfile.mkstemp(
    suffix='.npz', prefix=f'.{output.name}.', dir=output.parent
  )
  os.close(handle)
  try:
    policy.save(temporary)
    os.replace(temporary, output)
  except BaseException:
    pathlib.Path(temporary).unlink(missing_ok=True)
    raise
