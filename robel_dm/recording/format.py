"""The recording directory's files: writing an episode, reading them back."""

import dataclasses
import json
import os
import pathlib
import shutil
import time
from typing import Any

import numpy as np

FORMAT = 'robel_dm-recording'
VERSION = 1
# Free disk space a recording needs before anything moves, bytes.
MIN_FREE_BYTES = 50 * 1024 * 1024
# Buffered steps reach the disk at least this often, s: every step older
# than a second is on disk.
FLUSH_INTERVAL = 0.5  # Half the promised second, to keep clear of it.
CHUNK = 'data/chunk-000'
EPISODES = 'meta/episodes.jsonl'
INFO = 'meta/info.json'


class RecordingError(RuntimeError):
  """The recording cannot be written or read (named path)."""


@dataclasses.dataclass
class Episode:
  """A recorded episode.

  Attributes:
    metadata: its line of meta/episodes.jsonl (`complete` False for an
      episode that was cut short).
    steps: column -> array over time (list columns as 2-D arrays).
  """

  metadata: dict[str, Any]
  steps: dict[str, np.ndarray]

  def __len__(self) -> int:
    return len(next(iter(self.steps.values()))) if self.steps else 0


def require_pyarrow():
  """pyarrow with its IPC and Parquet modules.

  Raises:
    RecordingError: if the `data` extra is not installed.
  """
  try:
    import pyarrow  # noqa: PLC0415
    import pyarrow.ipc  # noqa: F401, PLC0415
    import pyarrow.parquet  # noqa: F401, PLC0415
  except ImportError as error:
    raise RecordingError(
      'recordings need pyarrow: pip install "robel_dm[data]"'
    ) from error
  return pyarrow


def prepare(directory: pathlib.Path) -> None:
  """Creates the directory and checks it is writable with room to spare.

  Raises:
    RecordingError: naming the directory and what is wrong.
  """
  try:
    (directory / CHUNK).mkdir(parents=True, exist_ok=True)
    (directory / 'meta').mkdir(exist_ok=True)
    probe = directory / 'meta' / '.write-probe'
    probe.write_bytes(b'robel_dm')
    probe.unlink()
  except OSError as error:
    raise RecordingError(
      f'cannot write a recording in {directory}: {error}'
    ) from error
  free = shutil.disk_usage(directory).free
  if free < MIN_FREE_BYTES:
    raise RecordingError(
      f'{directory}: only {free / 2**20:.0f} MiB free; a recording needs '
      f'{MIN_FREE_BYTES / 2**20:.0f} MiB'
    )


def next_index(directory: pathlib.Path) -> int:
  """The index the next episode gets (after every existing one)."""
  indices = [
    int(path.stem.split('_')[1])
    for path in (directory / CHUNK).glob('episode_*.*')
  ]
  return max(indices, default=-1) + 1


class EpisodeWriter:
  """Streams one episode's rows to an Arrow file; finishes it as Parquet."""

  def __init__(self, directory: pathlib.Path, index: int):
    self._pa = require_pyarrow()
    self.directory = directory
    self.index = index
    self.stream_path = directory / CHUNK / f'episode_{index:06d}.arrows'
    self.parquet_path = self.stream_path.with_suffix('.parquet')
    self._rows: list[dict] = []
    self._writer = None
    self._file = None
    self._last_flush = time.monotonic()
    self.length = 0

  def add(self, row: dict[str, Any]) -> None:
    self._rows.append(row)
    self.length += 1
    if time.monotonic() - self._last_flush >= FLUSH_INTERVAL:
      self.flush()

  def flush(self) -> None:
    """Writes the buffered rows as one record batch and flushes the file."""
    if not self._rows:
      return
    pa = self._pa
    try:
      batch = pa.RecordBatch.from_pylist(self._rows)
      if self._writer is None:
        self._file = pa.OSFile(str(self.stream_path), 'wb')
        self._writer = pa.ipc.new_stream(self._file, batch.schema)
      self._writer.write_batch(batch)
      self._file.flush()
    except (OSError, pa.ArrowException) as error:
      raise RecordingError(
        f'writing {self.stream_path} failed: {error}'
      ) from error
    self._rows.clear()
    self._last_flush = time.monotonic()

  def finish(self, metadata: dict[str, Any]) -> None:
    """Ends the episode: Parquet file, then its line in episodes.jsonl."""
    self.flush()
    if self._writer is None:
      return  # Nothing was recorded.
    pa = self._pa
    try:
      self._writer.close()
      self._file.close()
      with pa.ipc.open_stream(str(self.stream_path)) as reader:
        table = reader.read_all()
      partial = self.parquet_path.with_suffix('.parquet.partial')
      pa.parquet.write_table(table, str(partial))
      os.replace(partial, self.parquet_path)
      self.stream_path.unlink()
      line = json.dumps({**metadata, 'length': self.length}) + '\n'
      with open(self.directory / EPISODES, 'a') as file:
        file.write(line)
        file.flush()
        os.fsync(file.fileno())
    except (OSError, pa.ArrowException) as error:
      raise RecordingError(
        f'finishing {self.parquet_path} failed: {error}'
      ) from error


def _columns(table) -> dict[str, np.ndarray]:
  steps = {}
  for name in table.column_names:
    values = table.column(name).to_pylist()
    steps[name] = np.array(
      [np.nan if v is None else v for v in values]
      if values and not isinstance(values[0], list)
      else [v if v is not None else [] for v in values]
    )
  return steps


def _read_stream(path: pathlib.Path):
  """The complete record batches of a (possibly truncated) Arrow stream."""
  pa = require_pyarrow()
  batches = []
  try:
    with pa.ipc.open_stream(str(path)) as reader:
      for batch in reader:
        batches.append(batch)
  except (OSError, pa.ArrowException):
    pass  # A write cut short by a crash: keep what came before.
  return pa.Table.from_batches(batches) if batches else None


def read(directory: str | pathlib.Path) -> list[Episode]:
  """Every episode of a recording, in order; partial ones last-known.

  Raises:
    RecordingError: if the directory is not a recording.
  """
  directory = pathlib.Path(directory)
  if not (directory / INFO).is_file():
    raise RecordingError(f'{directory} is not a robel_dm recording')
  pa = require_pyarrow()
  lines = {}
  if (directory / EPISODES).is_file():
    for line in (directory / EPISODES).read_text().splitlines():
      if line.strip():
        entry = json.loads(line)
        lines[entry['episode_index']] = entry
  info = json.loads((directory / INFO).read_text())
  episodes = []
  for path in sorted((directory / CHUNK).glob('episode_*.*')):
    index = int(path.stem.split('_')[1])
    if path.suffix == '.parquet':
      table = pa.parquet.read_table(str(path))
      metadata = lines.get(index, {'episode_index': index, 'complete': False})
    elif path.suffix == '.arrows':
      table = _read_stream(path)
      if table is None:
        continue
      metadata = {
        **info.get('session', {}),
        **({'robot': info['robot']} if info.get('robot') else {}),
        'episode_index': index,
        'complete': False,
        'length': table.num_rows,
      }
    else:
      continue
    episodes.append(Episode(metadata, _columns(table)))
  return episodes


def summarize(directory: str | pathlib.Path) -> list[dict[str, Any]]:
  """One line per episode: index, steps, complete, success, return, safety."""
  rows = []
  for episode in read(directory):
    steps = episode.steps
    rewards = steps.get('next.reward', np.zeros(0))
    success = steps.get('observation.success')
    rows.append(
      {
        'episode': episode.metadata['episode_index'],
        'steps': len(episode),
        'complete': bool(episode.metadata.get('complete')),
        'success': bool(success[-1])
        if success is not None and len(success)
        else None,
        'return': float(np.nansum(rewards)),
        'safety': np.sum(steps['observation.safety'], axis=0).tolist()
        if 'observation.safety' in steps
        else None,
      }
    )
  return rows
