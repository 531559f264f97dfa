"""The recording directory's files, and writing an episode (reading them
back: `reader`).

What a kill leaves, by the instant it strikes (`EpisodeWriter.finish` does
these in order), and what `reader.read()` makes of it:

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
import hashlib
import json
import os
import pathlib
import re
import shutil
import threading
import time
from typing import IO, Any
import weakref
import zlib

import numpy as np

from robel_dm import constants

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
# `reader.describe_columns`).
COLUMNS_KEY = b'robel_dm.columns'
# The schema metadata key of the CRC-32 of the rest of the schema (column
# names and types, the other metadata), decimal: see `schema_checksum`.
SCHEMA_CHECKSUM_KEY = b'robel_dm.schema_crc32'
# The custom metadata key of a stream's record batch: the CRC-32 of the
# batch as Arrow serializes it, decimal.
BATCH_CHECKSUM_KEY = b'robel_dm.crc32'
# The episodes.jsonl key of the SHA-256 of the episode's Parquet file, hex.
PARQUET_CHECKSUM = 'parquet_sha256'
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
      'recordings need pyarrow: ' + constants.INSTALL_EXTRA.format('data')
    ) from error
  return pyarrow


def _type_name(pa, type_) -> str:
  """A column type as text, without a list's item name (Parquet renames
  it)."""
  if pa.types.is_list(type_):
    return f'list<{_type_name(pa, type_.value_type)}>'
  return str(type_)


def schema_checksum(pa, schema) -> bytes:
  """The CRC-32 of a schema's column names and types and its metadata (but
  SCHEMA_CHECKSUM_KEY's), as decimal text."""
  fields = [[field.name, _type_name(pa, field.type)] for field in schema]
  metadata = sorted(
    [key.hex(), value.hex()]
    for key, value in (schema.metadata or {}).items()
    if key != SCHEMA_CHECKSUM_KEY
  )
  return str(zlib.crc32(json.dumps([fields, metadata]).encode())).encode()


def batch_checksum(batch) -> bytes:
  """The CRC-32 of a record batch as Arrow serializes it, decimal text."""
  return str(zlib.crc32(batch.serialize())).encode()


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
    RecordingError: if another process records into the directory, or the
      lock file cannot be opened (e.g. another user's).
  """
  path = directory / LOCK
  try:
    handle = open(path, 'a+')  # noqa: SIM115 (held until the recorder closes)
  except OSError as error:
    raise RecordingError(f'cannot lock {directory}: {error}') from error
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


def episode_files(
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
  return max(episode_files(directory), default=-1) + 1


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
      columns: the description of the columns (see
        `reader.describe_columns`),
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
          schema = schema.with_metadata(
            {
              **self._schema_metadata,
              SCHEMA_CHECKSUM_KEY: schema_checksum(pa, schema),
            }
          )
          self._writer = pa.ipc.new_stream(self._file, schema)
        self._writer.write_batch(
          batch, custom_metadata={BATCH_CHECKSUM_KEY: batch_checksum(batch)}
        )
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
      sink = pa.BufferOutputStream()
      pa.parquet.write_table(table, sink, write_page_checksum=True)
      data = sink.getvalue()
      partial.write_bytes(data)
      fsync_file(partial)
      os.replace(partial, self.parquet_path)
      fsync_directory(chunk)
      self.stream_path.unlink()
      fsync_directory(chunk)
      line = {
        **metadata,
        'length': self.length,
        PARQUET_CHECKSUM: hashlib.sha256(data).hexdigest(),
      }
      line = json.dumps(line).encode() + b'\n'
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
