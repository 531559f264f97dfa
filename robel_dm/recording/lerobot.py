"""Exports a recording as a LeRobotDataset (codebase version v3.0 or v2.1).

A robel_dm recording stores dm_env timesteps: row k is the timestep after
step k together with the action that led to it (row 0 is the reset). A
LeRobotDataset stores frames: frame t is an observation, the action taken
from it, and what followed (`next.reward`, `next.done`). `export` converts
one into the other:

  frame t of an episode of N steps (t = 0 .. N-1):
    observation.*      row t's observations
    observation.state  row t's agent observation, flattened in the task's
                       order (what a policy sees)
    wall_time_elapsed  row t's wall-clock time less the episode's first
                       (s); the episode's start, float64 seconds since the
                       epoch, is its `wall_time_start` in the episode
                       metadata (LeRobot hands every float to torch as
                       float32, which would round epoch times to minutes)
    action             row t+1's action (the normalized action taken at t)
    joint_targets, next.reward, discount, next.done, reward_terms.*,
    motor.*            row t+1's values (what that action led to);
                       motor.timestamp and motor.health_timestamp as
                       seconds since the episode's first motor read (the
                       reset's health read), whose time.monotonic() is the
                       episode's `motor_time_start` (float32 would round
                       monotonic times to steps of 0.06 s after 10 days of
                       uptime)
    timestamp          row t's time, s (float64)
    index, episode_index, frame_index, task_index

Each episode's metadata also keeps its link to the recording:
`recording_episode_index` and, where the recording says, `episode_seed`
(the seed of the episode's reset, with which a replay reproduces it).

The episode's final observation (row N) has no action and is not a frame, as
in LeRobot's own recordings. Only complete episodes are exported. A column of
one value per frame is stored as a scalar and declared with shape [1] (how
LeRobot reads such a feature); vector features carry the names of their
dimensions (joint names, motor IDs) where the recording knows them;
observation.state names each of its dimensions uniquely, by the
observation it comes from ('claw_qpos.FFJ10', 'last_action.FFJ10',
'root_pos.x').

v3.0 (the default; what LeRobot 0.4 and later read) writes

  meta/info.json, meta/stats.json, meta/tasks.parquet,
  meta/episodes/chunk-000/file-000.parquet (one row per episode: its
    length, tasks, frame range, data file and per-feature statistics),
  data/chunk-{c:03d}/file-{f:03d}.parquet (episodes back to back; a new
    file once one holds about DATA_FILE_MB, 1000 files a chunk);

v2.1 (LeRobot 0.3) writes meta/info.json, meta/tasks.jsonl,
meta/episodes.jsonl, meta/episodes_stats.jsonl and one file per episode,
data/chunk-{c:03d}/episode_{e:06d}.parquet. Both also write
meta/robel_dm.json: where the data came from and each column's unit and
dimension names. No videos or images (robel_dm records none). See
docs/recording.md for what is tested, and how.
"""

import json
import os
import pathlib
import shutil
from typing import Any

import numpy as np

from robel_dm.recording import format as format_lib
from robel_dm.recording import reader

VERSIONS = ('v3.0', 'v2.1')
CHUNK_SIZE = 1000  # Files (v3.0) or episodes (v2.1) per chunk directory.
DATA_FILE_MB = 100  # v3.0: a data file's size before the next one starts.
V30_DATA_PATH = 'data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet'
V30_EPISODES_PATH = 'meta/episodes/chunk-000/file-000.parquet'
V21_DATA_PATH = (
  'data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet'
)
ROBEL_DM_META = 'meta/robel_dm.json'
# Per-frame columns every LeRobotDataset has.
INDEX_COLUMNS = ('timestamp', 'frame_index', 'episode_index', 'index',
                 'task_index')  # fmt: skip
# Columns taken from the row after the frame (what the frame's action led
# to); the others come from the frame's own row.
_NEXT_PREFIXES = ('action', 'joint_targets', 'next.', 'discount',
                  'reward_terms.', 'motor.')  # fmt: skip
# The dm_env step type, which frames replace.
_DROPPED = ('step_type',)
_DTYPES = {'f': 'float64', 'i': 'int64', 'u': 'int64', 'b': 'bool'}


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
  # One value per frame is a scalar column (LeRobot reads shape [1] so).
  return {
    k: v.reshape(len(v)) if v.ndim == 2 and v.shape[1] == 1 else v
    for k, v in frames.items()
  }


def _names(
  columns: dict[str, dict[str, Any]], keys
) -> dict[str, list[str] | None]:
  """Column -> its dimension names (None where unknown or a scalar).

  `observation.state` names each dimension by the observation it comes
  from, unique over the vector: 'upright' (one value), 'claw_qpos.FFJ10',
  'root_pos.x', or 'key[0]' where the recording does not name them.
  """
  names = {k: v.get('names') for k, v in columns.items()}
  if keys:
    state = []
    for key in keys:
      column = columns.get(f'observation.{key}', {})
      size = int(np.prod(column.get('shape') or [1]))
      known = column.get('names')
      if size == 1:
        state.append(key)
      elif known and len(known) == size:
        state += [f'{key}.{name}' for name in known]
      else:
        state += [f'{key}[{i}]' for i in range(size)]
    names['observation.state'] = state
  return names


def _feature(values: np.ndarray, names: list[str] | None) -> dict[str, Any]:
  shape = [1] if values.ndim == 1 else list(values.shape[1:])
  if names is not None and (len(shape) != 1 or len(names) != shape[0]):
    names = None  # Never declare names that do not fit the data.
  return {'dtype': _DTYPES[values.dtype.kind], 'shape': shape, 'names': names}


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


def _arrow_table(pa, columns: dict[str, np.ndarray]):
  return pa.table(
    {k: pa.array(v.tolist() if v.ndim > 1 else v) for k, v in columns.items()}
  )


def _description(directory: pathlib.Path, episode_index: int) -> dict:
  """The recording's description of its columns (empty if it has none)."""
  path = directory / format_lib.CHUNK / f'episode_{episode_index:06d}.parquet'
  try:
    return reader.describe_columns(path)
  except format_lib.RecordingError:
    return {}


def _episodes(directory: pathlib.Path):
  episodes = [
    e
    for e in reader.read(directory)
    if e.metadata.get('complete') and len(e) > 1
  ]
  if not episodes:
    raise format_lib.RecordingError(
      f'{directory} has no complete episode to export'
    )
  return episodes


# The motor clock's columns (time.monotonic(), s), exported as seconds since
# the episode's first motor read: in float32, as LeRobot hands them to
# torch, monotonic times are rounded to 0.06 s after 10 days of uptime.
_MOTOR_TIMES = ('motor.timestamp', 'motor.health_timestamp')


def _relative_times(episode: format_lib.Episode, columns: dict) -> dict:
  """Makes the wall-clock and motor-clock columns relative to the episode's
  start; returns the starts (float64), for the episode's metadata."""
  wall_time = columns.pop('wall_time')
  columns['wall_time_elapsed'] = wall_time - wall_time[0]
  starts = {'wall_time_start': float(wall_time[0])}
  first_reads = [
    episode.steps[name][0] for name in _MOTOR_TIMES if name in episode.steps
  ]  # Row 0's: the reset's reads, its health read first.
  if first_reads and np.isfinite(first_reads).any():
    start = float(np.nanmin(first_reads))
    for name in _MOTOR_TIMES:
      if name in columns:
        columns[name] = columns[name] - start
    starts['motor_time_start'] = start
  return starts


def _links(metadata: dict[str, Any]) -> dict[str, Any]:
  """What ties an exported episode to its recording: the recording's
  episode index and, where it says, the seed of the episode's reset."""
  links = {'recording_episode_index': metadata['episode_index']}
  if metadata.get('episode_seed') is not None:
    links['episode_seed'] = metadata['episode_seed']
  return links


def _converted(directory, episodes, keys, names, features: dict):
  """Yields each episode's (index, task, task index, episode metadata,
  columns); fills `features` from the first and checks the others."""
  tasks: dict[str, int] = {}
  total_frames = 0
  for episode_index, episode in enumerate(episodes):
    frames = _frames(episode, keys)
    length = len(next(iter(frames.values())))
    task = _task_name(episode.metadata)
    task_index = tasks.setdefault(task, len(tasks))
    columns = {
      'timestamp': np.asarray(episode.steps['timestamp'][:-1], np.float64),
      'frame_index': np.arange(length),
      'episode_index': np.full(length, episode_index),
      'index': np.arange(total_frames, total_frames + length),
      'task_index': np.full(length, task_index),
      **frames,
    }
    metadata = {
      **_relative_times(episode, columns),
      **_links(episode.metadata),
    }
    episode_features = {
      k: _feature(v, names.get(k)) for k, v in columns.items()
    }
    if not features:
      features.update(episode_features)
    elif episode_features != features:
      raise format_lib.RecordingError(
        f'{directory}: episode {episode.metadata["episode_index"]} has other '
        'columns than the first; export one task per dataset'
      )
    total_frames += length
    yield episode_index, task, task_index, metadata, columns


def export(
  directory: str | os.PathLike,
  output: str | os.PathLike,
  version: str = 'v3.0',
) -> dict[str, Any]:
  """Writes the recording's complete episodes as a LeRobotDataset.

  Args:
    directory: a robel_dm recording.
    output: the dataset's directory (must not exist yet).
    version: the LeRobotDataset codebase version, 'v3.0' (LeRobot 0.4 and
      later) or 'v2.1' (LeRobot 0.3).

  Returns:
    The dataset's meta/info.json.

  Raises:
    RecordingError: if `output` exists or its folder does not, the
      recording has no complete episode, its episodes differ in columns, or
      writing fails (nothing is left at `output` then).
    ValueError: for another `version`.
  """
  if version not in VERSIONS:
    raise ValueError(
      f'LeRobotDataset version {version!r}: robel_dm writes '
      + ' or '.join(VERSIONS)
    )
  pa = format_lib.require_pyarrow()
  directory, output = pathlib.Path(directory), pathlib.Path(output)
  if output.exists():
    raise format_lib.RecordingError(f'{output} exists; export writes a new one')
  if not output.parent.is_dir():
    raise format_lib.RecordingError(f'no folder {output.parent} for {output}')
  info = _required_info(directory)
  episodes = _episodes(directory)
  staging = output.with_name(output.name + '.partial')
  shutil.rmtree(staging, ignore_errors=True)
  try:
    dataset_info = _stage(pa, staging, directory, info, episodes, version)
    os.replace(staging, output)
  except (OSError, KeyError, pa.ArrowException) as error:
    # Disk full, no permission, an info.json without what it must hold.
    shutil.rmtree(staging, ignore_errors=True)
    raise format_lib.RecordingError(
      f'writing {output} failed: {type(error).__name__}: {error}'
    ) from error
  return dataset_info


def _stage(pa, staging, directory, info, episodes, version) -> dict[str, Any]:
  """Writes the dataset into `staging`; returns its meta/info.json."""
  keys = info.get('observation_keys')
  description = _description(directory, episodes[0].metadata['episode_index'])
  columns = description.get('columns', {})
  (staging / 'meta').mkdir(parents=True)
  features = {}
  converted = _converted(
    directory, episodes, keys, _names(columns, keys), features
  )
  write = _write_v30 if version == 'v3.0' else _write_v21
  tasks, frames = write(pa, staging, converted)
  dataset_info = _dataset_info(
    version, info['fps'], episodes, tasks, frames, features
  )
  (staging / format_lib.INFO).write_text(json.dumps(dataset_info, indent=1))
  (staging / ROBEL_DM_META).write_text(
    json.dumps(
      {
        'source': str(directory),
        'observation_keys': list(keys or ()),
        'provenance': info.get('provenance'),
        'robot': info.get('robot'),
        # Units and dimension names, as the recording's files describe them
        # (see recording.describe_columns).
        'columns': columns,
      },
      indent=1,
    )
  )
  return dataset_info


def _required_info(directory: pathlib.Path) -> dict[str, Any]:
  """The recording's info.json, which an export needs (the reader goes on
  without a damaged one; a dataset cannot)."""
  try:
    info = json.loads((directory / format_lib.INFO).read_text())
  except (OSError, ValueError) as error:
    info = error
  if not isinstance(info, dict):
    raise format_lib.RecordingError(
      f'{directory} is not a readable recording ({format_lib.INFO}: {info})'
    )
  return info


def _dataset_info(
  version: str, fps, episodes, tasks: dict, frames: int, features: dict
) -> dict[str, Any]:
  """The dataset's meta/info.json (v3.0 also gives every feature the
  fps)."""
  dataset_info = {
    'codebase_version': version,
    'robot_type': episodes[0].metadata.get('domain'),
    'total_episodes': len(episodes),
    'total_frames': frames,
    'total_tasks': len(tasks),
    'chunks_size': CHUNK_SIZE,
    'fps': int(fps) if float(fps).is_integer() else fps,
    'splits': {'train': f'0:{len(episodes)}'},
    'video_path': None,
    'features': features,
  }
  if version == 'v3.0':
    dataset_info.update(
      data_files_size_in_mb=DATA_FILE_MB,
      video_files_size_in_mb=DATA_FILE_MB,
      data_path=V30_DATA_PATH,
    )
    for feature in features.values():
      feature['fps'] = dataset_info['fps']
  else:
    dataset_info.update(
      total_videos=0,
      total_chunks=(len(episodes) - 1) // CHUNK_SIZE + 1,
      data_path=V21_DATA_PATH,
    )
  return dataset_info


def _write_v21(pa, staging: pathlib.Path, converted):
  """One Parquet file per episode; JSON-lines metadata."""
  tasks, frames = {}, 0
  with (
    open(staging / format_lib.EPISODES, 'w') as episodes_file,
    open(staging / 'meta/episodes_stats.jsonl', 'w') as stats_file,
  ):
    for episode_index, task, task_index, metadata, columns in converted:
      tasks[task] = task_index
      length = len(columns['index'])
      path = staging / V21_DATA_PATH.format(
        episode_chunk=episode_index // CHUNK_SIZE, episode_index=episode_index
      )
      path.parent.mkdir(parents=True, exist_ok=True)
      pa.parquet.write_table(_arrow_table(pa, columns), str(path))
      episodes_file.write(
        json.dumps(
          {
            'episode_index': episode_index,
            'tasks': [task],
            'length': length,
            **metadata,
          }
        )
        + '\n'
      )
      stats = {k: _stats(v) for k, v in columns.items()}
      stats_file.write(
        json.dumps({'episode_index': episode_index, 'stats': stats}) + '\n'
      )
      frames += length
  with open(staging / 'meta/tasks.jsonl', 'w') as tasks_file:
    for task, task_index in tasks.items():
      tasks_file.write(
        json.dumps({'task_index': task_index, 'task': task}) + '\n'
      )
  return tasks, frames


def _write_v30(pa, staging: pathlib.Path, converted):
  """Episodes back to back in size-bounded files; Parquet metadata."""
  tasks = {}
  rows = []  # One per episode, for meta/episodes.
  pending, pending_bytes = [], 0  # Episodes of the data file being filled.
  file_number, frames = 0, 0
  every_column: dict[str, list[np.ndarray]] = {}

  def flush():
    nonlocal pending, pending_bytes, file_number
    if not pending:
      return
    path = staging / V30_DATA_PATH.format(
      chunk_index=file_number // CHUNK_SIZE,
      file_index=file_number % CHUNK_SIZE,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    pa.parquet.write_table(pa.concat_tables(pending), str(path))
    pending, pending_bytes = [], 0
    file_number += 1

  for episode_index, task, task_index, metadata, columns in converted:
    tasks[task] = task_index
    table = _arrow_table(pa, columns)
    if pending and pending_bytes + table.nbytes > DATA_FILE_MB * 2**20:
      flush()
    pending.append(table)
    pending_bytes += table.nbytes
    length = len(columns['index'])
    row = {
      'episode_index': episode_index,
      'tasks': [task],
      'length': length,
      'data/chunk_index': file_number // CHUNK_SIZE,
      'data/file_index': file_number % CHUNK_SIZE,
      'dataset_from_index': frames,
      'dataset_to_index': frames + length,
      'meta/episodes/chunk_index': 0,
      'meta/episodes/file_index': 0,
      **metadata,
    }
    for name, values in columns.items():
      for stat, value in _stats(values).items():
        row[f'stats/{name}/{stat}'] = value
      every_column.setdefault(name, []).append(values)
    rows.append(row)
    frames += length
  flush()
  episodes_path = staging / V30_EPISODES_PATH
  episodes_path.parent.mkdir(parents=True)
  # Every key of any row (from_pylist would keep the first row's): an
  # episode without a seed among episodes with one gets a null.
  keys = dict.fromkeys(key for row in rows for key in row)
  table = pa.table({key: [row.get(key) for row in rows] for key in keys})
  pa.parquet.write_table(table, str(episodes_path))
  stats = {k: _stats(np.concatenate(v)) for k, v in every_column.items()}
  (staging / 'meta/stats.json').write_text(json.dumps(stats, indent=1))
  _write_tasks(pa, staging / 'meta/tasks.parquet', tasks)
  return tasks, frames


def _write_tasks(pa, path: pathlib.Path, tasks: dict[str, int]) -> None:
  """meta/tasks.parquet as pandas writes a frame indexed by task text
  (LeRobot reads it with pandas.read_parquet; pandas is not needed here)."""
  index = '__index_level_0__'
  pandas_metadata = {
    'index_columns': [index],
    'column_indexes': [
      {
        'name': None,
        'field_name': None,
        'pandas_type': 'unicode',
        'numpy_type': 'object',
        'metadata': {'encoding': 'UTF-8'},
      }
    ],  # fmt: skip
    'columns': [
      {
        'name': 'task_index',
        'field_name': 'task_index',
        'pandas_type': 'int64',
        'numpy_type': 'int64',
        'metadata': None,
      },
      {
        'name': None,
        'field_name': index,
        'pandas_type': 'unicode',
        'numpy_type': 'object',
        'metadata': None,
      },
    ],  # fmt: skip
    'creator': {'library': 'pyarrow', 'version': pa.__version__},
    'pandas_version': '2.2.3',
  }
  table = pa.table(
    {
      'task_index': pa.array(list(tasks.values()), pa.int64()),
      index: pa.array(list(tasks), pa.string()),
    }
  ).replace_schema_metadata({'pandas': json.dumps(pandas_metadata)})
  pa.parquet.write_table(table, str(path))
