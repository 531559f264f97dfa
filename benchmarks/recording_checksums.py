"""What writing and reading one episode file costs, and the checksums' part.

Records one D'Claw Turn Fixed episode (40 steps of seeded random actions,
41 rows) in simulation, then, with fsync off (its cost is the disk's, see
benchmarks/recording_cost.py), times in one process, minimum over
`--repeats`:

  write    EpisodeWriter: the 41 rows added and flushed 10 at a time (a
           robot's 0.5 s at 20 Hz), then finished (the Parquet file and
           its episodes.jsonl line)
  read     recording.read of a directory holding that finished episode,
           and of one holding it as a stream (an episode cut short)

and, where the installed robel_dm writes checksums, their parts: the
CRC-32 of each flushed record batch and of the schema, the SHA-256 of the
Parquet file, the Parquet page CRCs (writing and verifying). Run it on an
older robel_dm (PYTHONPATH) for the times without checksums and checks.

    MUJOCO_GL=egl python benchmarks/recording_checksums.py [--repeats 200]
"""

import argparse
import hashlib
import io
import pathlib
import shutil
import tempfile
import time

import numpy as np

from robel_dm import recording, suite
from robel_dm.recording import format as format_lib

BATCH = 10  # Rows per flush.


def _best(function, repeats: int) -> float:
  """The fastest of `repeats` calls, ms."""
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    function()
    times.append(time.perf_counter() - start)
  return min(times) * 1e3


def _episode(root: pathlib.Path):
  """A recorded episode's rows, metadata and description of its columns."""
  env = recording.Recorder(
    suite.load('dclaw', 'turn_fixed', seed=0), root / 'source',
    metadata={'domain': 'dclaw', 'task': 'turn_fixed'},
  )  # fmt: skip
  rng = np.random.default_rng(0)
  try:
    timestep = env.reset()
    while not timestep.last():
      timestep = env.step(rng.uniform(-1, 1, 9))
  finally:
    env.close()
  path = next((root / 'source' / format_lib.CHUNK).glob('*.parquet'))
  import pyarrow.parquet as pq  # noqa: PLC0415

  table = pq.read_table(path)
  (episode,) = recording.read(root / 'source')
  return table.to_pylist(), episode.metadata, recording.describe_columns(path)


def _prepare(directory: pathlib.Path) -> None:
  """An empty recording directory with the source's meta/info.json."""
  shutil.rmtree(directory, ignore_errors=True)
  format_lib.prepare(directory)
  source = directory.parent / 'source' / format_lib.INFO
  shutil.copy(source, directory / format_lib.INFO)


def _write(directory: pathlib.Path, rows, metadata, columns) -> None:
  _prepare(directory)
  writer = format_lib.EpisodeWriter(directory, 0, metadata, columns)
  for i, row in enumerate(rows):
    writer.add(row)
    if i % BATCH == BATCH - 1:
      writer.flush()
  writer.finish(metadata)


def _parts(pa, rows, directory: pathlib.Path, repeats: int) -> dict:
  """The checksums' parts of writing and reading the episode, ms."""
  batches = [
    pa.RecordBatch.from_pylist(rows[i : i + BATCH])
    for i in range(0, len(rows), BATCH)
  ]
  table = pa.Table.from_batches(batches)
  data = format_lib.episode_files(directory)[0]['parquet'].read_bytes()

  def parquet(checksums: bool) -> None:
    pa.parquet.write_table(table, io.BytesIO(), write_page_checksum=checksums)

  def read_parquet(checksums: bool) -> None:
    pa.parquet.read_table(
      pa.BufferReader(data), page_checksum_verification=checksums
    )

  batch_crcs = _best(
    lambda: [format_lib.batch_checksum(b) for b in batches], repeats
  )
  page_write = _best(lambda: parquet(True), repeats) - _best(
    lambda: parquet(False), repeats
  )
  page_read = _best(lambda: read_parquet(True), repeats) - _best(
    lambda: read_parquet(False), repeats
  )
  return {
    f'CRC-32 of {len(batches)} record batches (each written and read)': (
      batch_crcs
    ),
    'CRC-32 of the schema': _best(
      lambda: format_lib.schema_checksum(pa, table.schema), repeats
    ),
    f'SHA-256 of the Parquet file ({len(data)} bytes)': _best(
      lambda: hashlib.sha256(data).hexdigest(), repeats
    ),
    'Parquet page CRCs, writing (difference)': page_write,
    'Parquet page CRCs, verifying (difference)': page_read,
  }


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--repeats', type=int, default=200)
  args = parser.parse_args()
  pa = format_lib.require_pyarrow()
  format_lib.FSYNC = False
  root = pathlib.Path(tempfile.mkdtemp(prefix='recording_checksums_'))
  try:
    rows, metadata, columns = _episode(root)
    finished, streamed = root / 'finished', root / 'streamed'
    write = _best(
      lambda: _write(finished, rows, metadata, columns), args.repeats
    )
    _prepare(streamed)
    writer = format_lib.EpisodeWriter(streamed, 0, metadata, columns)
    for i, row in enumerate(rows):
      writer.add(row)
      if i % BATCH == BATCH - 1:
        writer.flush()
    writer.flush()
    writer._stop_timer()  # noqa: SLF001 (left unfinished: a stream)
    read_finished = _best(lambda: recording.read(finished), args.repeats)
    read_stream = _best(lambda: recording.read(streamed), args.repeats)
    print(f'D\'Claw Turn Fixed, {len(rows)} rows, flushed {BATCH} at a time, '
          f'fsync off; min of {args.repeats} (ms):')  # fmt: skip
    print(f'  write and finish an episode: {write:.3f}')
    print(f'  read it (Parquet file):      {read_finished:.3f}')
    print(f'  read it (stream):            {read_stream:.3f}')
    if hasattr(format_lib, 'batch_checksum'):
      for name, value in _parts(pa, rows, finished, args.repeats).items():
        print(f'  {name}: {value:.3f}')
  finally:
    shutil.rmtree(root, ignore_errors=True)


if __name__ == '__main__':
  main()
