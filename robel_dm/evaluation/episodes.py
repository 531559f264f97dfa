"""The episodes of an evaluation: one episode's loop, the serial run of a
sequence of them (filmed or not), and the summary of their records.

`run_episode` is the loop that every evaluation (serial, worker processes,
Ray tasks) runs; `Tally` gathers the episodes' records into the results.
"""

from collections.abc import Callable, Sequence
import dataclasses
import math
import os
import time
from typing import Any

from absl import logging
import numpy as np

from robel_dm import gl_backend, policies, provenance, recording, robots, video
from robel_dm.tasks import base

# A frame slower than this is software rendering: the note says so.
SLOW_FRAME_SECONDS = 0.05


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


def summarize(
  records: list[dict[str, Any]],
  head: dict[str, Any],
  steps_per_second: float,
) -> dict[str, Any]:
  """The result of a run: `head`, the means and spreads, the records."""

  def values(key):
    return [r[key] for r in records]

  requested = head.get('episodes_requested', len(records))
  return {
    **head,
    'episodes': len(records),
    # False while a run is under way, and in the output of a run cut short.
    'complete': len(records) >= requested,
    'success_rate': float(np.mean(values('success'))) if records else math.nan,
    'mean_return': float(np.mean(values('return'))) if records else math.nan,
    'mean_score': float(np.mean(values('mean_score'))) if records else math.nan,
    'mean_final_score': float(np.mean(values('final_score')))
    if records
    else math.nan,
    'safety': {
      field: float(np.mean([r['safety'][field] for r in records]))
      if records
      else math.nan
      for field in base.SAFETY_FIELDS
    },
    'spread': {
      'success': provenance.proportion(values('success')),
      'return': provenance.spread(values('return')),
      'mean_score': provenance.spread(values('mean_score')),
    },
    'steps_per_second': steps_per_second,
    'records': records,
  }


class Tally:
  """The records of a run as its episodes end, and its results so far.

  Attributes:
    head: what the results start with (the task, policy, seed, ...).
    records: the episodes' records, in episode order.
  """

  def __init__(
    self,
    head: dict[str, Any],
    on_episode: Callable[[dict[str, Any]], None] | None = None,
  ):
    """Starts an empty tally.

    Args:
      head: what the results start with (see `summarize`).
      on_episode: called with the results so far after every episode.
    """
    self.head = head
    self.records: list[dict[str, Any]] = []
    self._on_episode = on_episode
    self._steps = 0
    self._step_seconds = 0.0

  def add(self, record: dict[str, Any], steps: int, seconds: float) -> None:
    """Counts one more episode (its record, steps and step seconds)."""
    self.records.append(record)
    self._steps += steps
    self._step_seconds += seconds
    if self._on_episode is not None:
      self._on_episode(self.results())

  def results(self) -> dict[str, Any]:
    """The results so far (see `summarize`)."""
    seconds = self._step_seconds
    rate = self._steps / seconds if seconds else math.nan
    return summarize(self.records, self.head, rate)


@dataclasses.dataclass(frozen=True)
class Films:
  """Which episodes are filmed, into which folder, by which camera.

  Attributes:
    directory: the videos' folder.
    camera: the camera, as the model names it (None before `open_films`:
      the domain's default).
    episodes: the indices of the filmed episodes.
    domain: the task's domain (the default camera's, and the videos' names).
    task: the task (the videos' names).
  """

  directory: str
  camera: str | None
  episodes: frozenset[int]
  domain: str
  task: str

  def path(self, episode: int) -> str:
    """The video file of episode `episode`."""
    name = f'{self.domain}_{self.task}_{episode:04d}.mp4'
    return os.path.join(self.directory, name)


def open_films(
  env,
  films: Films,
  log: Callable[[str], None] | None = None,
) -> Films:
  """Checks the camera and makes the folder before the first episode.

  Args:
    env: the environment (a frame is rendered to time the renderer).
    films: what to film (its `camera` None: the domain's default).
    log: called with one line on how the videos are rendered and how long
      they will take; None: no line.

  Returns:
    `films`, with its camera named.

  Raises:
    video.VideoError: for a camera the model does not have.
  """
  camera = films.camera or robots.ROBOTS[films.domain].default_camera
  video.check_camera(env, camera)
  os.makedirs(films.directory, exist_ok=True)
  if log is not None:
    log(_rendering_note(env, camera, len(films.episodes)))
  return dataclasses.replace(films, camera=camera)


def _rendering_note(env, camera: str, videos: int) -> str:
  """How videos are rendered here and what they will cost: one line."""
  video.render(env, camera)  # The first frame also sets the renderer up.
  start = time.perf_counter()
  video.render(env, camera)
  seconds = time.perf_counter() - start
  steps = env.task.episode_steps
  minutes = seconds * (steps + 1) * videos / 60
  note = (
    f'videos: camera {camera}, {gl_backend.describe()}; {seconds:.2f} s a '
    f'frame here, about {minutes:.1f} min for {videos} episode(s) of '
    f'{steps} steps'
  )
  if seconds > SLOW_FRAME_SECONDS:
    note += ' (software rendering: --video_episodes films fewer)'
  return note


def run_serial(
  env,
  act: Callable[[int | None], policies.Policy],
  seeds: Sequence[int | None],
  tally: Tally,
  films: Films | None = None,
  log_every: int = 0,
) -> None:
  """Runs the episodes one after another in `env`, into `tally`.

  Args:
    env: the environment (a `recording.Recorder` is told each episode's
      seed).
    act: the policy of an episode, given its seed.
    seeds: each episode's reset seed (None continues the random state).
    tally: receives each episode's record.
    films: the filmed episodes (see `open_films`); None films none.
    log_every: log progress every this many episodes (0: never).
  """
  for episode, episode_seed in enumerate(seeds):
    writer = on_step = None
    if films is not None and episode in films.episodes:
      path = films.path(episode)
      writer = video.VideoWriter(path, fps=1 / env.control_timestep())

      def on_step(writer=writer):
        writer.add(video.render(env, films.camera))

    policy = act(episode_seed)
    if isinstance(env, recording.Recorder):  # What a replay checks.
      env.annotate(episode_seed=episode_seed)
    try:
      record, steps, seconds = run_episode(env, policy, episode_seed, on_step)
    finally:
      if writer is not None:
        writer.close()
    if writer is not None:
      record['video'] = path
    tally.add(record, steps, seconds)
    if log_every and (episode + 1) % log_every == 0:
      logging.info(
        '%s/%s: %d/%d episodes, success so far %.2f',
        tally.head['domain'],
        tally.head['task'],
        episode + 1,
        len(seeds),
        np.mean([r['success'] for r in tally.records]),
      )
