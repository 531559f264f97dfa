"""Demonstrations: recorded episodes as (observation, action, ...) arrays.

A demonstration set is a recording (`evaluate --record=DIR`, with the
reference controller or a solved policy) of the task being learned. Only
complete episodes count; a recording of another task is refused.
"""

import dataclasses
import pathlib

import numpy as np

from robel_dm import recording
from robel_dm.tasks import base


@dataclasses.dataclass(frozen=True)
class Transitions:
  """Aligned arrays, one row per transition.

  Attributes:
    observations: (n, obs) the agent vector an action was taken from.
    actions: (n, act) the normalized action.
    rewards: (n,) ROBEL's reward that followed.
    next_observations: (n, obs) the agent vector after the action.
    terminals: (n,) True where the task ended the episode (a fall), not
      the time limit.
    episodes: how many episodes they came from.
    violations: (n,) the safety violations (all kinds summed) of the step
      that led to each transition; None if unknown.
  """

  observations: np.ndarray
  actions: np.ndarray
  rewards: np.ndarray
  next_observations: np.ndarray
  terminals: np.ndarray
  episodes: int
  violations: np.ndarray | None = None

  def __len__(self) -> int:
    return len(self.actions)


def concatenate(parts: list[Transitions]) -> Transitions:
  """One set of transitions from several, in order. Their violations, if
  any part has them, count 0 in the parts without."""
  fields = ('observations', 'actions', 'rewards', 'next_observations',
            'terminals')  # fmt: skip
  violations = None
  if any(part.violations is not None for part in parts):
    violations = np.concatenate(
      [
        np.zeros(len(part), np.float32)
        if part.violations is None
        else part.violations
        for part in parts
      ]
    )
  return Transitions(
    *(np.concatenate([getattr(part, f) for part in parts]) for f in fields),
    episodes=sum(part.episodes for part in parts),
    violations=violations,
  )


class DemoError(ValueError):
  """A demonstration set that cannot be used."""


def _check_variant(directory, recorded: dict, task_kwargs: dict | None) -> None:
  """Raises DemoError unless the recording was made under the run's
  interface options (`base.INTERFACE_OPTIONS`: another valve or action map
  gives an action another meaning)."""
  for option, theirs, ours in base.interface_differences(recorded, task_kwargs):
    raise DemoError(
      f'demonstrations in {directory} were made with {option} {theirs}, '
      f'not {ours}'
    )


def load(
  directories: str | pathlib.Path | list,
  domain: str,
  task: str,
  observation_keys: tuple[str, ...],
  task_kwargs: dict | None = None,
  episodes: int | None = None,
  complete_only: bool = True,
) -> Transitions:
  """The complete episodes of one or more recordings of `domain/task`.

  Args:
    directories: recording directories.
    domain: the task's domain.
    task: the task.
    observation_keys: the agent vector's keys, in order.
    task_kwargs: the task's arguments (the valve must match).
    episodes: use the first this many complete episodes (all if None).
    complete_only: False also takes the steps of episodes a fault or an
      interruption ended (their last transition is not terminal).

  Raises:
    DemoError: a directory is not a recording of this task, holds too few
      complete episodes, or lacks an observation key.
  """
  if isinstance(directories, (str, pathlib.Path)):
    directories = [directories]
  chosen = []
  for directory in directories:
    try:
      recorded = recording.read(directory)
    except recording.RecordingError as error:
      raise DemoError(f'demonstrations: {error}') from error
    for episode in recorded:
      meta = episode.metadata
      if (meta.get('domain'), meta.get('task')) != (domain, task):
        raise DemoError(
          f'demonstrations in {directory} are of {meta.get("domain")}/'
          f'{meta.get("task")}, not {domain}/{task}'
        )
      _check_variant(directory, meta.get('task_kwargs') or {}, task_kwargs)
      if (meta.get('complete') or not complete_only) and len(episode) > 1:
        chosen.append(episode)
  if episodes is not None:
    if len(chosen) < episodes:
      raise DemoError(
        f'{len(chosen)} complete demonstration episodes, {episodes} asked'
      )
    chosen = chosen[:episodes]
  if not chosen:
    raise DemoError(
      'no complete demonstration episode'
      if complete_only
      else 'no recorded transition'
    )
  parts = [_transitions(episode, observation_keys) for episode in chosen]
  return concatenate(parts)


def _transitions(episode, keys) -> Transitions:
  """One recorded episode's transitions (with their violations if the
  recording has the safety observation)."""
  steps = episode.steps
  missing = [k for k in keys if f'observation.{k}' not in steps]
  if missing:
    raise DemoError(f'demonstrations lack observations {missing}')
  flat = np.concatenate(
    [
      np.asarray(steps[f'observation.{key}'], np.float32).reshape(
        len(episode), -1
      )
      for key in keys
    ],
    axis=1,
  )
  # Row t holds the action that led to it and the reward that followed;
  # the first row is the reset's.
  actions = np.asarray(steps['action'], np.float32)[1:]
  rewards = np.asarray(steps['next.reward'], np.float32)[1:]
  discounts = np.asarray(steps['discount'], np.float32)[1:]
  terminals = np.zeros(len(actions), bool)
  terminals[-1] = discounts[-1] == 0
  violations = None
  if 'observation.safety' in steps:
    safety = np.asarray(steps['observation.safety'], np.float32)
    violations = safety.reshape(len(episode), -1)[1:].sum(axis=1)
  return Transitions(
    flat[:-1], actions, rewards, flat[1:], terminals, 1, violations
  )
