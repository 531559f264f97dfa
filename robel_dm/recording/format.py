"""The recording directory's files: writing an episode, reading them back.

What a kill leaves, by the instant it strikes (`EpisodeWriter.finish` does
these in order), and what `read()` makes of it:

  mid-episode         episode_N.arrows with every flushed batch: the episode,
                      `complete` False, metadata from the stream's schema
  writing Parquet     episode_N.parquet.partial beside the stream: the
                      partial file is ignored (a warning), the stream read
  renamed             episode_N.parquet and the stream: the Parquet file,
                      once
  stream unlinked     episode_N.parquet without its episodes.jsonl line:
                      `complete` False, metadata from the Parquet schema
"""

import dataclasses
import fcntl
import json
import os
import pathlib
import re
import shutil
import threading
import time
from typing import IO, Any
import warnings
import weakref

import numpy as np

FORMAT = 'robel_dm-recording'
VERSION = 1
# Free disk space a recording needs before anything moves, bytes.
MIN_FREE_BYTES = 50 * 1024 * 1024
# Buffered steps reach the disk at least this often, s: every step older
# than a second is on disk.
FLUSH_INTERVAL = 0.5  # Half the promised second, to keep clear of it.
# Whether writes are fsynced (the stream after each flush, the Parquet file
# before its rename, the directory after a rename or unlink, the
# episodes.jsonl line). Off, a kill of the process loses nothing more, but
# a power cut may lose what the operating system had not yet written.
FSYNC = True
CHUNK = 'data/chunk-000'
EPISODES = 'meta/episodes.jsonl'
INFO = 'meta/info.json'
# The schema metadata key of an episode's stream (and Parquet file): the
# episode's metadata as known at its start, JSON.
METADATA_KEY = b'robel_dm.episode'
# The schema metadata key of the description of an episode's columns, JSON:
# domain, task, task_kwargs, fps and `columns`, column -> unit, shape per
# row and (vector columns) the names of its dimensions (see
# `describe_columns`).
COLUMNS_KEY = b'robel_dm.columns'
_EPISODE_FILE = re.compile(r'episode_(\d+)\.(arrows|parquet|parquet\.partial)')


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


def fsync_file(path: pathlib.Path) -> None:
  """Makes a written file's data durable (if FSYNC)."""
  if FSYNC:
    descriptor = os.open(path, os.O_RDONLY)
    try:
      os.fsync(descriptor)
    finally:
      os.close(descriptor)


def fsync_directory(path: pathlib.Path) -> None:
  """Makes the entries of a directory (a rename, a new or deleted file)
  durable (if FSYNC; POSIX only)."""
  flag = getattr(os, 'O_DIRECTORY', None)
  if FSYNC and flag is not None:
    descriptor = os.open(path, os.O_RDONLY | flag)
    try:
      os.fsync(descriptor)
    finally:
      os.close(descriptor)


def write_atomically(path: pathlib.Path, text: str) -> None:
  """Replaces `path` with `text`: a kill leaves the old file or the new."""
  partial = path.with_name(path.name + '.partial')
  partial.write_text(text)
  fsync_file(partial)
  os.replace(partial, path)
  fsync_directory(path.parent)


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
    # The new directories' entries (in their parents), so that a power cut
    # keeps them.
    for path in ((directory / CHUNK).parent, directory, directory.parent):
      fsync_directory(path)
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


LOCK = 'meta/.lock'


def lock(directory: pathlib.Path) -> IO[str]:
  """Takes the directory's recording lock: one recorder at a time, since
  two would number their episodes alike. The operating system releases it
  when the file closes or the process ends, however it ends.

  Returns:
    The lock file; close it to release the lock.

  Raises:
    RecordingError: if another process records into the directory.
  """
  path = directory / LOCK
  handle = open(path, 'a+')  # noqa: SIM115 (held until the recorder closes)
  try:
    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
  except OSError:
    handle.seek(0)
    holder = handle.read().strip() or 'unknown'
    handle.close()
    raise RecordingError(
      f'{directory} is being recorded by another process (pid {holder}); '
      'record into another directory, or wait for it to finish'
    ) from None
  handle.seek(0)
  handle.truncate()
  handle.write(str(os.getpid()))
  handle.flush()
  return handle


def _episode_files(
  directory: pathlib.Path,
) -> dict[int, dict[str, pathlib.Path]]:
  """Episode index -> kind ('arrows', 'parquet', 'parquet.partial') -> path."""
  files: dict[int, dict[str, pathlib.Path]] = {}
  chunk = directory / CHUNK
  if chunk.is_dir():
    for path in chunk.iterdir():
      match = _EPISODE_FILE.fullmatch(path.name)
      if match:
        files.setdefault(int(match[1]), {})[match[2]] = path
  return files


def next_index(directory: pathlib.Path) -> int:
  """The index the next episode gets: after every episode file there,
  streams and unfinished Parquet files included."""
  return max(_episode_files(directory), default=-1) + 1


def _flush_when_idle(writer_ref, stop: threading.Event) -> None:
  """The timer of an EpisodeWriter: flushes rows a stalled loop left
  buffered, FLUSH_INTERVAL after the last flush; ends on `stop` (or when the
  writer is gone or failed)."""
  delay = FLUSH_INTERVAL
  while not stop.wait(delay):
    writer = writer_ref()
    if writer is None:
      return
    delay = writer.flush_if_idle()
    del writer
    if delay is None:
      return


class EpisodeWriter:
  """Streams one episode's rows to an Arrow file; finishes it as Parquet.

  Rows are written when `add` finds the last flush FLUSH_INTERVAL old, and
  by a daemon thread when no row arrives to do it (a stalled loop); the
  thread ends with `finish`. `_lock` guards the buffered rows (held only to
  add or take them); `_write_lock` orders the writes, so `add` does not wait
  for the thread's fsync unless it flushes too.
  """

  def __init__(
    self,
    directory: pathlib.Path,
    index: int,
    metadata: dict[str, Any] | None = None,
    columns: dict[str, Any] | None = None,
  ):
    """Starts an episode (its stream is created at the first flush).

    Args:
      directory: the recording directory.
      index: the episode's index.
      metadata: the episode's metadata as known at its start, stored in
        the stream's schema (what `read` reports if the episode never
        finishes).
      columns: the description of the columns (see `describe_columns`),
        stored in the schema of the stream and of the Parquet file.
    """
    self._pa = require_pyarrow()
    self.directory = directory
    self.index = index
    self.stream_path = directory / CHUNK / f'episode_{index:06d}.arrows'
    self.parquet_path = self.stream_path.with_suffix('.parquet')
    self._metadata = {**(metadata or {}), 'episode_index': index}
    self._schema_metadata = {
      METADATA_KEY: json.dumps(self._metadata).encode()
    }  # Encoded once: the stream's schema is made at the first flush.
    if columns is not None:
      self._schema_metadata[COLUMNS_KEY] = json.dumps(columns).encode()
    self._rows: list[dict] = []
    self._writer = None
    self._file = None
    self._last_flush = time.monotonic()
    self._error: RecordingError | None = None
    self._lock = threading.Lock()
    self._write_lock = threading.Lock()
    self._stop = threading.Event()
    self._timer = threading.Thread(
      target=_flush_when_idle,
      args=(weakref.ref(self), self._stop),
      name=f'recording-flush-{index}',
      daemon=True,
    )
    self._timer.start()
    self.length = 0

  def _raise_timer_error(self) -> None:
    if self._error is not None:
      raise self._error

  def add(self, row: dict[str, Any]) -> None:
    with self._lock:
      self._raise_timer_error()
      self._rows.append(row)
      self.length += 1
      due = time.monotonic() - self._last_flush >= FLUSH_INTERVAL
    if due:
      self.flush()

  def flush(self) -> None:
    """Writes the buffered rows as one record batch, flushes and fsyncs."""
    with self._write_lock:
      with self._lock:
        self._raise_timer_error()
        rows, self._rows = self._rows, []
      if not rows:
        return
      pa = self._pa
      try:
        batch = pa.RecordBatch.from_pylist(rows)
        created = self._writer is None
        if created:
          self._file = pa.OSFile(str(self.stream_path), 'wb')
          schema = batch.schema.with_metadata(self._schema_metadata)
          self._writer = pa.ipc.new_stream(self._file, schema)
        self._writer.write_batch(batch)
        self._file.flush()
        if FSYNC:
          os.fsync(self._file.fileno())
        if created:
          fsync_directory(self.stream_path.parent)
      except (OSError, pa.ArrowException) as error:
        with self._lock:
          self._rows[:0] = rows  # Kept for another try.
        raise RecordingError(
          f'writing {self.stream_path} failed: {error}'
        ) from error
      self._last_flush = time.monotonic()

  def flush_if_idle(self) -> float | None:
    """Flushes if the last flush is FLUSH_INTERVAL old (the timer's work).

    Returns:
      Seconds until the next check, or None if a write failed (the error
      is raised by the next add, flush or finish).
    """
    delay = self._last_flush + FLUSH_INTERVAL - time.monotonic()
    if delay <= 0:
      delay = FLUSH_INTERVAL
      if self._rows:
        try:
          self.flush()
        except RecordingError as error:
          self._error = error
          return None
    return max(delay, 0.01)  # No spinning, whatever the interval.

  def _stop_timer(self) -> None:
    self._stop.set()
    if self._timer is not threading.current_thread():
      self._timer.join()

  def finish(self, metadata: dict[str, Any]) -> None:
    """Ends the episode: Parquet file, then its line in episodes.jsonl.

    Each step is durable before the next (see the module docstring for
    what a kill between them leaves).
    """
    self._stop_timer()
    self.flush()
    if self._writer is None:
      return  # Nothing was recorded.
    pa = self._pa
    chunk = self.stream_path.parent
    try:
      self._writer.close()
      self._file.close()
      with pa.ipc.open_stream(str(self.stream_path)) as reader:
        table = reader.read_all()  # Its schema keeps the metadata.
      partial = self.parquet_path.with_name(self.parquet_path.name + '.partial')
      pa.parquet.write_table(table, str(partial))
      fsync_file(partial)
      os.replace(partial, self.parquet_path)
      fsync_directory(chunk)
      self.stream_path.unlink()
      fsync_directory(chunk)
      line = json.dumps({**metadata, 'length': self.length}).encode() + b'\n'
      path = self.directory / EPISODES
      created = not path.exists()
      with open(path, 'a+b') as file:
        size = file.seek(0, os.SEEK_END)
        if size:
          file.seek(size - 1)
          if file.read(1) != b'\n':  # Torn: start a line of our own.
            line = b'\n' + line
        file.write(line)
        file.flush()
        if FSYNC:
          os.fsync(file.fileno())
      if created:
        fsync_directory(path.parent)
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
  schema = None
  try:
    with pa.ipc.open_stream(str(path)) as reader:
      schema = reader.schema
      for batch in reader:
        batches.append(batch)
  except (OSError, pa.ArrowException):
    pass  # A write cut short by a crash: keep what came before.
  if not batches:
    return None
  return pa.Table.from_batches(batches, schema=schema)


def _stored_metadata(table) -> dict[str, Any] | None:
  """The episode metadata in a stream's or Parquet file's schema."""
  stored = (table.schema.metadata or {}).get(METADATA_KEY)
  try:
    metadata = json.loads(stored) if stored else None
  except ValueError:
    return None
  return metadata if isinstance(metadata, dict) else None


def describe_columns(path: str | pathlib.Path) -> dict[str, Any]:
  """The description an episode file carries of its columns (a Parquet
  file, or an `.arrows` stream), read from the file alone.

  Returns:
    domain, task, task_kwargs (what the recorder was told; None where it
    was not), task_class, fps and `columns`: column -> {'unit': the unit
    ('rad', 'rad/s', 's', 'mA', 'degC', 'V', 'm', 'm/s'; '' if unitless,
    None if unknown), 'shape': the shape of one row's value ([] for a
    scalar, [n] for a vector), 'names': a vector's dimension names (joint
    names, motor IDs, axes; None if unknown)}.

  Raises:
    RecordingError: if the file is unreadable or carries no description
      (recorded before robel_dm described its columns).
  """
  pa = require_pyarrow()
  path = pathlib.Path(path)
  try:
    if path.suffix == '.arrows':
      with pa.ipc.open_stream(str(path)) as reader:
        schema = reader.schema
    else:
      schema = pa.parquet.read_schema(str(path))
  except (OSError, pa.ArrowException) as error:
    raise RecordingError(f'cannot read {path}: {error}') from error
  stored = (schema.metadata or {}).get(COLUMNS_KEY)
  try:
    description = json.loads(stored) if stored else None
  except ValueError:
    description = None
  if not isinstance(description, dict):
    raise RecordingError(
      f'{path} has no description of its columns (recorded before '
      'robel_dm described them; docs/recording.md lists their units)'
    )
  return description


def _read_lines(directory: pathlib.Path) -> dict[int, dict[str, Any]]:
  """Episode index -> its episodes.jsonl line; a damaged line is skipped."""
  lines = {}
  path = directory / EPISODES
  if not path.is_file():
    return lines
  text = path.read_bytes().decode('utf-8', errors='replace')
  for number, line in enumerate(text.splitlines(), 1):
    if not line.strip():
      continue
    try:
      entry = json.loads(line)
      lines[int(entry['episode_index'])] = entry
    except (ValueError, TypeError, KeyError) as error:
      warnings.warn(
        f'{path} line {number} is damaged ({error}); skipped',
        stacklevel=3,
      )
  return lines


def _read_info(directory: pathlib.Path) -> dict[str, Any]:
  path = directory / INFO
  try:
    info = json.loads(path.read_text())
  except (OSError, ValueError) as error:
    warnings.warn(f'{path} is unreadable ({error}); ignored', stacklevel=3)
    return {}
  return info if isinstance(info, dict) else {}


def read(directory: str | pathlib.Path) -> list[Episode]:
  """Every episode of a recording, in order; partial ones last-known.

  A damaged file costs only its episode, with a warning naming it: a
  leftover `.parquet.partial` is ignored (the episode is read from its
  stream if that is still there), an unreadable Parquet file falls back to
  its stream (or the episode is skipped), a damaged episodes.jsonl line is
  skipped. An episode with both a Parquet file and a stream (a kill between
  the rename and the unlink) is read once, from the Parquet file.

  Raises:
    RecordingError: if the directory is not a recording.
  """
  directory = pathlib.Path(directory)
  if not (directory / INFO).is_file():
    raise RecordingError(f'{directory} is not a robel_dm recording')
  pa = require_pyarrow()
  lines = _read_lines(directory)
  info = _read_info(directory)
  session = {
    **info.get('session', {}),
    **({'robot': info['robot']} if info.get('robot') else {}),
  }  # What a stream of an older version, without its own metadata, gets.
  episodes = []
  for index, files in sorted(_episode_files(directory).items()):
    if 'parquet.partial' in files:
      warnings.warn(
        f'{files["parquet.partial"]} is an unfinished Parquet file (the '
        'process stopped while writing it); ignored',
        stacklevel=2,
      )
    table = None
    if 'parquet' in files:
      try:
        table = pa.parquet.read_table(str(files['parquet']))
      except (OSError, pa.ArrowException) as error:
        fallback = 'read from its stream' if 'arrows' in files else 'skipped'
        warnings.warn(
          f'{files["parquet"]} is unreadable ({error}); episode {index} '
          f'{fallback}',
          stacklevel=2,
        )
    if table is None and 'arrows' in files:
      table = _read_stream(files['arrows'])
    if table is None:
      continue
    metadata = lines.get(index)
    if metadata is None:  # Cut short, or killed before its line.
      metadata = {
        **(_stored_metadata(table) or session),
        'episode_index': index,
        'complete': False,
        'length': table.num_rows,
      }
    episodes.append(Episode(metadata, _columns(table)))
  return episodes


def summarize(directory: str | pathlib.Path) -> list[dict[str, Any]]:
  """One line per episode: index, steps, complete, success, return, safety.

  Safety is the violations summed over the steps after the reset (the
  reset's row, step_type FIRST, is not counted), as `evaluate` counts them.
  """
  rows = []
  for episode in read(directory):
    steps = episode.steps
    rewards = steps.get('next.reward', np.zeros(0))
    success = steps.get('observation.success')
    safety = steps.get('observation.safety')
    if safety is not None:
      step_types = steps.get('step_type', np.zeros(0))
      first = int(len(step_types) > 0 and step_types[0] == 0)  # dm_env FIRST
      safety = np.sum(safety[first:], axis=0).tolist()
    rows.append(
      {
        'episode': episode.metadata['episode_index'],
        'steps': len(episode),
        'complete': bool(episode.metadata.get('complete')),
        'success': bool(success[-1])
        if success is not None and len(success)
        else None,
        'return': float(np.nansum(rewards)),
        'safety': safety,
      }
    )
  return rows
