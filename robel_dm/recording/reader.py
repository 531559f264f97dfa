"""Reading a recording back, every file checked before a column is read.

What damage `read()` finds (a damaged file costs its episode, or a stream
the rows from the damage on, with a warning naming it): a finished Parquet
file whose SHA-256 differs from its episodes.jsonl line's (any change, if
the line is there), a Parquet page whose CRC-32 differs, a schema (column
names, types, metadata) whose CRC-32 differs, a stream record batch whose
CRC-32 differs, and, whatever the checksums say, arrays that fail Arrow's
full validation, list columns whose rows differ in length from the
description, missing values, and episode or frame indices out of sequence.
docs/recording.md says what is not detected.
"""

import hashlib
import json
import pathlib
from typing import Any
import warnings

import numpy as np

from robel_dm.recording.format import (
  BATCH_CHECKSUM_KEY,
  COLUMNS_KEY,
  EPISODES,
  INFO,
  METADATA_KEY,
  PARQUET_CHECKSUM,
  SCHEMA_CHECKSUM_KEY,
  Episode,
  RecordingError,
  batch_checksum,
  episode_files,
  require_pyarrow,
  schema_checksum,
)


class _DamageError(Exception):
  """What is wrong with an episode file (raised before a column is read)."""


def _read_errors(pa) -> tuple[type[BaseException], ...]:
  """What reading a damaged file may raise, besides _DamageError."""
  return (pa.ArrowException, OSError, ValueError, TypeError, LookupError,
          MemoryError)  # fmt: skip


def _schema_intact(pa, schema) -> bool:
  """Whether a schema matches the checksum it carries (one without a
  checksum cannot be checked, and passes)."""
  checksum = (schema.metadata or {}).get(SCHEMA_CHECKSUM_KEY)
  return checksum is None or checksum == schema_checksum(pa, schema)


def _check_schema(pa, schema) -> dict[str, Any] | None:
  """Checks an episode file's schema against its checksum and its
  description of its columns.

  Returns:
    The description's `columns` (None for a file without one: the oldest
    recordings).

  Raises:
    _DamageError: naming what does not fit.
  """
  stored = schema.metadata or {}
  if not _schema_intact(pa, schema):
    raise _DamageError('its schema does not match its checksum')
  for field in schema:
    type_ = field.type
    if pa.types.is_list(type_):
      type_ = type_.value_type
    if not (pa.types.is_integer(type_) or pa.types.is_floating(type_)
            or pa.types.is_boolean(type_)):  # fmt: skip
      raise _DamageError(f'column {field.name!r} is of type {field.type}')
  if COLUMNS_KEY not in stored:
    return None
  try:
    columns = json.loads(stored[COLUMNS_KEY])['columns']
    shapes = {name: list(columns[name]['shape']) for name in schema.names}
  except (ValueError, TypeError, KeyError) as error:
    raise _DamageError(
      f'its description of its columns is damaged ({error})'
    ) from None
  if len(columns) != len(shapes):
    raise _DamageError('its columns are not those its description lists')
  for field in schema:
    if pa.types.is_list(field.type) != (len(shapes[field.name]) == 1):
      raise _DamageError(
        f'column {field.name!r} is of type {field.type}, its description '
        f'says shape {shapes[field.name]}'
      )
  return columns


def _check_rows(pa, data, index: int, first_row: int, widths: dict) -> None:
  """Checks an episode's rows (a record batch or a table) before any value
  is read: valid Arrow arrays, no missing value, every row of a list column
  `widths[column]` long (set from the first rows if not given), the
  episode's index, and frame indices counting on from `first_row`.

  Raises:
    _DamageError: naming what does not fit.
  """
  try:
    data.validate(full=True)
  except pa.ArrowException as error:
    raise _DamageError(f'invalid arrays: {error}') from None
  for field in data.schema:
    column = data.column(field.name)
    if column.null_count:
      raise _DamageError(f'column {field.name!r} has missing values')
    if not pa.types.is_list(field.type):
      continue
    for chunk in getattr(column, 'chunks', [column]):  # A table's, a batch's.
      if chunk.flatten().null_count:
        raise _DamageError(f'column {field.name!r} has missing values')
      lengths = np.diff(chunk.offsets.to_numpy())
      width = widths.setdefault(field.name, lengths[0] if len(lengths) else 0)
      if np.any(lengths != width):
        raise _DamageError(
          f'column {field.name!r} has rows of other lengths than {width}'
        )
  names = data.schema.names
  if 'episode_index' in names and np.any(
    data.column('episode_index').to_numpy() != index
  ):
    raise _DamageError(f'its episode_index column is not all {index}')
  rows = np.arange(first_row, first_row + data.num_rows)
  if 'frame_index' in names and not np.array_equal(
    data.column('frame_index').to_numpy(), rows
  ):
    raise _DamageError(
      f'its frame_index column does not count on from {first_row}'
    )


def _widths(columns: dict[str, Any] | None) -> dict[str, int]:
  """List column -> its rows' length, from a description's columns."""
  return {
    name: column['shape'][0]
    for name, column in (columns or {}).items()
    if len(column['shape']) == 1
  }


def _read_parquet(pa, path: pathlib.Path, index: int, line: dict | None):
  """An episode's checked Parquet file, as a table.

  Raises:
    _DamageError, or one of `_read_errors`: what is wrong with it.
  """
  data = path.read_bytes()
  expected = (line or {}).get(PARQUET_CHECKSUM)
  if expected is not None and hashlib.sha256(data).hexdigest() != expected:
    raise _DamageError(
      f'its SHA-256 is not the one on its line of {EPISODES}: the file or '
      'that line is damaged'
    )
  # ParquetFile, not read_table: no Arrow worker thread is started, none
  # left to abort the interpreter's exit (apache/arrow#34314).
  file = pa.parquet.ParquetFile(
    pa.BufferReader(data), page_checksum_verification=True
  )
  table = file.read(use_threads=False)
  widths = _widths(_check_schema(pa, table.schema))
  _check_rows(pa, table, index, 0, widths)
  return table


def _read_stream(pa, path: pathlib.Path, index: int):
  """An episode's stream, up to its first damaged or cut-short record
  batch (a write cut short by a crash, or damage), checked.

  Returns:
    The table of the rows before it (None if none), and what is wrong at
    that batch (None if the stream ends there).
  """
  batches, rows, schema = [], 0, None
  try:
    # Read whole: a damaged length cannot make the reader allocate more.
    with pa.ipc.open_stream(pa.BufferReader(path.read_bytes())) as reader:
      schema = reader.schema
      widths = _widths(_check_schema(pa, schema))
      checked = SCHEMA_CHECKSUM_KEY in (schema.metadata or {})
      while True:
        try:
          batch, custom = reader.read_next_batch_with_custom_metadata()
        except StopIteration:
          break
        _check_rows(pa, batch, index, rows, widths)
        stored = (custom or {}).get(BATCH_CHECKSUM_KEY)
        if checked and stored != batch_checksum(batch):
          raise _DamageError(
            f'rows {rows} to {rows + batch.num_rows - 1} do not match their '
            'checksum'
          )
        batches.append(batch)
        rows += batch.num_rows
  except _DamageError as error:
    problem = str(error)
  except _read_errors(pa) as error:
    problem = f'{type(error).__name__}: {error}'
  else:
    problem = None
  table = pa.Table.from_batches(batches, schema=schema) if batches else None
  return table, problem


def _columns(table) -> dict[str, np.ndarray]:
  """Column -> its values (a checked table: no missing values, list
  columns of equal rows)."""
  return {
    name: np.array(table.column(name).to_pylist())
    for name in table.column_names
  }


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
    RecordingError: if the file is unreadable, its schema does not match
      its checksum, or it carries no description (recorded before robel_dm
      described its columns).
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
  if not _schema_intact(pa, schema):
    raise RecordingError(
      f'{path} is damaged: its schema does not match its checksum'
    )
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


def _episode_table(pa, index: int, files: dict[str, pathlib.Path], line):
  """An episode's checked rows as a table (None if none are readable),
  each damaged or unfinished file named in a warning."""
  if 'parquet.partial' in files:
    warnings.warn(
      f'{files["parquet.partial"]} is an unfinished Parquet file (the '
      'process stopped while writing it); ignored',
      stacklevel=3,
    )
  if 'parquet' in files:
    try:
      return _read_parquet(pa, files['parquet'], index, line)
    except (_DamageError, *_read_errors(pa)) as error:
      fallback = 'read from its stream' if 'arrows' in files else 'skipped'
      warnings.warn(
        f'{files["parquet"]} is damaged or unreadable ({error}); episode '
        f'{index} {fallback}',
        stacklevel=3,
      )
  if 'arrows' not in files:
    return None
  table, problem = _read_stream(pa, files['arrows'], index)
  if problem is not None:
    rows = 0 if table is None else table.num_rows
    warnings.warn(
      f'{files["arrows"]} is damaged or cut short after {rows} rows '
      f'({problem}); episode {index} '
      + ('skipped' if table is None else 'read up to there'),
      stacklevel=3,
    )
  return table


def read(directory: str | pathlib.Path) -> list[Episode]:
  """Every episode of a recording, in order; partial ones last-known.

  A damaged file costs only its episode, with a warning naming it, and is
  found before its columns are read (see the module docstring for what is
  checked): a leftover `.parquet.partial` is ignored (the episode is read
  from its stream if that is still there), a damaged or unreadable Parquet
  file falls back to its stream (or the episode is skipped), a stream is
  read up to its first damaged or cut-short record batch, a damaged
  episodes.jsonl line is skipped. An episode with both a Parquet file and
  a stream (a kill between the rename and the unlink) is read once, from
  the Parquet file.

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
  for index, files in sorted(episode_files(directory).items()):
    table = _episode_table(pa, index, files, lines.get(index))
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

  Steps are the control steps after the reset, and safety the violations
  summed over them, as `evaluate` counts them: the reset's row (step_type
  FIRST) is neither.
  """
  rows = []
  for episode in read(directory):
    steps = episode.steps
    rewards = steps.get('next.reward', np.zeros(0))
    success = steps.get('observation.success')
    safety = steps.get('observation.safety')
    step_types = steps.get('step_type', np.zeros(0))
    first = int(len(step_types) > 0 and step_types[0] == 0)  # dm_env FIRST
    if safety is not None:
      safety = np.sum(safety[first:], axis=0).tolist()
    rows.append(
      {
        'episode': episode.metadata['episode_index'],
        'steps': len(episode) - first,
        'complete': bool(episode.metadata.get('complete')),
        'success': bool(success[-1])
        if success is not None and len(success)
        else None,
        'return': float(np.nansum(rewards)),
        'safety': safety,
      }
    )
  return rows
