"""Exports a recording as a LeRobotDataset (codebase version v2.1).

A robel_dm recording stores dm_env timesteps: row k is the timestep after
step k together with the action that led to it (row 0 is the reset). A
LeRobotDataset stores frames: frame t is an observation, the action taken
from it, and what followed (`next.reward`, `next.done`). `export` converts
one into the other:

  frame t of an episode of N steps (t = 0 .. N-1):
    observation.*      row t's observations
    observation.state  row t's agent observation, flattened in the task's
                       order (what a policy sees)
    wall_time          row t's
    action             row t+1's action (the normalized action taken at t)
    joint_targets, next.reward, discount, next.done, reward_terms.*,
    motor.*            row t+1's values (what that action led to)
    timestamp          row t's time, s
    index, episode_index, frame_index, task_index

The episode's final observation (row N) has no action and is not a frame, as
in LeRobot's own recordings. Only complete episodes are exported. Written:

  meta/info.json, meta/tasks.jsonl, meta/episodes.jsonl,
  meta/episodes_stats.jsonl,
  data/chunk-{chunk:03d}/episode_{index:06d}.parquet (1000 episodes a chunk)

No videos or images (robel_dm records none). See docs/recording.md for what
is and is not tested against LeRobot.
"""

import json
import os
import pathlib
import shutil
from typing import Any

import numpy as np

from robel_dm.recording import format as format_lib

CODEBASE_VERSION = 'v2.1'
CHUNK_SIZE = 1000  # Episodes per data/chunk-NNN directory.
DATA_PATH = 'data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet'
# Per-frame columns every LeRobotDataset has.
INDEX_COLUMNS = ('timestamp', 'frame_index', 'episode_index', 'index',
                 'task_index')  # fmt: skip
# Columns taken from the row after the frame (what the frame's action led
# to); the others come from the frame's own row.
_NEXT_PREFIXES = ('action', 'joint_targets', 'next.', 'discount',
                  'reward_terms.', 'motor.')  # fmt: skip
# The dm_env step type, which frames replace.
_DROPPED = ('step_type',)


def _task_name(metadata: dict[str, Any]) -> str:
  domain = metadata.get('domain', 'unknown')
  task = metadata.get('task') or metadata.get('kind') or 'unknown'
  return f'{domain}/{task}'


def _is_next(column: str) -> bool:
  return any(
    column == prefix or column.startswith(prefix) for prefix in _NEXT_PREFIXES
  )


def _frames(episode: format_lib.Episode, keys) -> dict[str, np.ndarray]:
  """The episode's LeRobot frames (without the index columns)."""
  steps = episode.steps
  frames = {}
  for column, values in steps.items():
    if column in INDEX_COLUMNS or column in _DROPPED:
      continue
    frames[column] = values[1:] if _is_next(column) else values[:-1]
  if keys:
    frames['observation.state'] = np.concatenate(
      [
        np.asarray(steps[f'observation.{key}'], float).reshape(len(episode), -1)
        for key in keys
      ],
      axis=1,
    )[:-1]
  return frames


def _feature(values: np.ndarray) -> dict[str, Any]:
  dtype = {'f': 'float64', 'i': 'int64', 'u': 'int64', 'b': 'bool'}[
    values.dtype.kind
  ]
  shape = [1] if values.ndim == 1 else list(values.shape[1:])
  return {'dtype': dtype, 'shape': shape, 'names': None}


def _stats(values: np.ndarray) -> dict[str, list]:
  array = np.asarray(values, float)
  if array.ndim == 1:
    array = array[:, None]
  return {
    'min': np.min(array, axis=0).tolist(),
    'max': np.max(array, axis=0).tolist(),
    'mean': np.mean(array, axis=0).tolist(),
    'std': np.std(array, axis=0).tolist(),
    'count': [len(array)],
  }


def export(
  directory: str | os.PathLike, output: str | os.PathLike
) -> dict[str, Any]:
  """Writes the recording's complete episodes as a LeRobotDataset v2.1.

  Args:
    directory: a robel_dm recording.
    output: the dataset's directory (must not exist yet).

  Returns:
    The dataset's meta/info.json.

  Raises:
    RecordingError: if `output` exists, the recording has no complete
      episode, or its episodes differ in columns.
  """
  pa = format_lib.require_pyarrow()
  output = pathlib.Path(output)
  if output.exists():
    raise format_lib.RecordingError(f'{output} exists; export writes a new one')
  info = json.loads((pathlib.Path(directory) / format_lib.INFO).read_text())
  episodes = [
    e for e in format_lib.read(directory) if e.metadata.get('complete')
  ]
  episodes = [e for e in episodes if len(e) > 1]
  if not episodes:
    raise format_lib.RecordingError(
      f'{directory} has no complete episode to export'
    )
  keys = info.get('observation_keys')
  fps = info['fps']
  tasks: dict[str, int] = {}
  features = None
  total_frames = 0
  staging = output.with_name(output.name + '.partial')
  shutil.rmtree(staging, ignore_errors=True)
  (staging / 'meta').mkdir(parents=True)
  with (
    open(staging / format_lib.EPISODES, 'w') as episodes_file,
    open(staging / 'meta/episodes_stats.jsonl', 'w') as stats_file,
  ):
    for episode_index, episode in enumerate(episodes):
      frames = _frames(episode, keys)
      length = len(next(iter(frames.values())))
      task = _task_name(episode.metadata)
      task_index = tasks.setdefault(task, len(tasks))
      columns = {
        'timestamp': episode.steps['timestamp'][:-1],
        'frame_index': np.arange(length),
        'episode_index': np.full(length, episode_index),
        'index': np.arange(total_frames, total_frames + length),
        'task_index': np.full(length, task_index),
        **frames,
      }
      episode_features = {k: _feature(v) for k, v in columns.items()}
      if features is None:
        features = episode_features
      elif episode_features != features:
        raise format_lib.RecordingError(
          f'{directory}: episode {episode.metadata["episode_index"]} has other '
          'columns than the first; export one task per dataset'
        )
      path = staging / DATA_PATH.format(
        episode_chunk=episode_index // CHUNK_SIZE, episode_index=episode_index
      )
      path.parent.mkdir(parents=True, exist_ok=True)
      table = pa.table(
        {
          k: pa.array(v.tolist() if v.ndim > 1 else v)
          for k, v in columns.items()
        }
      )
      pa.parquet.write_table(table, str(path))
      episodes_file.write(
        json.dumps(
          {'episode_index': episode_index, 'tasks': [task], 'length': length}
        )
        + '\n'
      )
      stats = {k: _stats(v) for k, v in columns.items()}
      stats_file.write(
        json.dumps({'episode_index': episode_index, 'stats': stats}) + '\n'
      )
      total_frames += length
  with open(staging / 'meta/tasks.jsonl', 'w') as tasks_file:
    for task, task_index in tasks.items():
      tasks_file.write(
        json.dumps({'task_index': task_index, 'task': task}) + '\n'
      )
  dataset_info = {
    'codebase_version': CODEBASE_VERSION,
    'robot_type': episodes[0].metadata.get('domain'),
    'total_episodes': len(episodes),
    'total_frames': total_frames,
    'total_tasks': len(tasks),
    'total_videos': 0,
    'total_chunks': (len(episodes) - 1) // CHUNK_SIZE + 1,
    'chunks_size': CHUNK_SIZE,
    'fps': int(fps) if float(fps).is_integer() else fps,
    'splits': {'train': f'0:{len(episodes)}'},
    'data_path': DATA_PATH,
    'video_path': None,
    'features': features,
    'robel_dm': {
      'source': str(directory),
      'observation_keys': list(keys or ()),
      'provenance': info.get('provenance'),
      'robot': info.get('robot'),
    },
  }
  (staging / format_lib.INFO).write_text(json.dumps(dataset_info, indent=1))
  os.replace(staging, output)
  return dataset_info
