"""Damaged recording files: each costs only its own episode (a stream, the
rows from the damage on), named in a warning, found before a column is read:
never a crash, an exception for the whole directory, or a damaged value
returned. Random bit flips in the streams and Parquet files of both robots
(benchmarks/recording_damage.py, run here with fewer flips)."""

import importlib
import json
import pathlib
import shutil
import struct
import subprocess
import sys
import warnings

import numpy as np
import pytest

pa = pytest.importorskip('pyarrow', reason='needs robel_dm[data]')

import pyarrow.ipc  # noqa: E402, F401
import pyarrow.parquet as pq  # noqa: E402

from robel_dm import evaluation, recording, suite  # noqa: E402
from robel_dm.recording import format as format_lib  # noqa: E402

_BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / 'benchmarks'
STREAM_ROWS = 11  # The episode in progress: the reset's row and 10 steps.

# recording.read in a child process, so that a crash fails the test (with
# its exit status) rather than killing pytest.
_READ = """
import json, sys, warnings
from robel_dm import recording
with warnings.catch_warnings(record=True) as caught:
  warnings.simplefilter('always')
  episodes = recording.read(sys.argv[1])
print(json.dumps({
  'episodes': [[e.metadata['episode_index'], len(e)] for e in episodes],
  'warnings': [str(w.message) for w in caught],
}))
"""


@pytest.fixture(scope='module')
def snapshot(tmp_path_factory):
  """Three finished D'Claw episodes and a fourth being recorded (its
  stream, one record batch per row), as a kill would leave them."""
  root = tmp_path_factory.mktemp('damage')
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 3, policy='random', seed=0, record=root / 'rec'
    )
  )
  with pytest.MonkeyPatch.context() as patch:
    patch.setattr(format_lib, 'FLUSH_INTERVAL', 0.0)  # A batch per row.
    env = recording.Recorder(
      suite.load('dclaw', 'pose_fixed', seed=3),
      root / 'rec',
      metadata={'domain': 'dclaw', 'task': 'pose_fixed'},
    )
    try:
      env.reset()
      rng = np.random.default_rng(0)
      for _ in range(STREAM_ROWS - 1):
        env.step(rng.uniform(-1, 1, 9))
      shutil.copytree(root / 'rec', root / 'snapshot')
    finally:
      env.close()
  return root / 'snapshot'


@pytest.fixture
def copy(snapshot, tmp_path):
  """A fresh copy of the snapshot, and its read (none warns)."""
  directory = tmp_path / 'rec'
  shutil.copytree(snapshot, directory)
  episodes, messages = _read(directory)
  assert messages == []
  assert [len(e) for e in episodes] == [81, 81, 81, STREAM_ROWS]
  return directory, episodes


def _read(directory):
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter('always')
    episodes = recording.read(directory)
  return episodes, [str(w.message) for w in caught]


def _read_in_child(directory) -> dict:
  done = subprocess.run(
    [sys.executable, '-c', _READ, str(directory)],
    capture_output=True, text=True, timeout=120, check=False,
  )  # fmt: skip
  assert done.returncode == 0, (
    f'read() exited with {done.returncode}: {done.stderr[-2000:]}'
  )
  return json.loads(done.stdout)


def _path(directory, index: int, suffix: str) -> pathlib.Path:
  return directory / format_lib.CHUNK / f'episode_{index:06d}.{suffix}'


def _assert_equal_steps(steps, expected, rows: int) -> None:
  assert set(steps) == set(expected)
  for name, values in steps.items():
    np.testing.assert_array_equal(values, expected[name][:rows], name)


def _without_line_checksums(directory) -> None:
  """Episodes' lines as a version without the Parquet checksum wrote them
  (the checks of the file alone then decide)."""
  path = directory / format_lib.EPISODES
  lines = [json.loads(line) for line in path.read_text().splitlines()]
  for line in lines:
    line.pop('parquet_sha256', None)
  path.write_text(''.join(json.dumps(line) + '\n' for line in lines))


@pytest.mark.slow
def test_a_list_row_of_the_wrong_length_costs_only_its_episode(copy):
  directory, _ = copy
  _without_line_checksums(directory)
  path = _path(directory, 1, 'parquet')
  table = pq.read_table(path)
  rows = table.to_pylist()
  rows[5]['observation.qpos'] = rows[5]['observation.qpos'][:-1]
  pq.write_table(pa.Table.from_pylist(rows, schema=table.schema), path)
  episodes, messages = _read(directory)
  assert [e.metadata['episode_index'] for e in episodes] == [0, 2, 3]
  (message,) = messages
  assert str(path) in message and 'episode 1 skipped' in message
  assert "'observation.qpos' has rows of other lengths than 9" in message
  # The summary command says so in one line, and lists the others.
  done = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.recording', str(directory)],
    capture_output=True, text=True, timeout=120, check=False,
  )  # fmt: skip
  assert done.returncode == 0, done.stderr
  assert done.stderr.splitlines() == [f'warning: {message}']
  assert f'3 episodes, {80 + 80 + STREAM_ROWS - 1} steps' in done.stdout
  # So does the export, of the others (the complete ones).
  out = directory.parent / f'{directory.name}_lerobot'
  exported = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.recording', str(directory),
     f'--lerobot={out}'],
    capture_output=True, text=True, timeout=120, check=False,
  )  # fmt: skip
  assert exported.returncode == 0, exported.stderr
  assert exported.stderr.splitlines() == [f'warning: {message}']


@pytest.mark.slow
def test_a_stream_batch_pointing_past_its_data_is_named_not_a_crash(copy):
  # List offsets out of bounds: the reader used to read far past the
  # batch's data (a segmentation fault) rather than validate it first.
  directory, episodes = copy
  path = _path(directory, 3, 'arrows')
  data = path.read_bytes()
  source = pa.BufferReader(data)
  with pa.ipc.open_stream(source) as reader:
    for _ in range(5):  # Rows 0 to 4 kept as they are.
      reader.read_next_batch()
    end = source.tell()
    bad = pa.Table.from_batches(list(reader)).combine_chunks()
  bad = bad.to_batches()[0]
  i = bad.schema.get_field_index('observation.qpos')
  offsets = np.arange(bad.num_rows + 1, dtype=np.int32) * 9
  offsets[2] = 2**30
  damaged = pa.Array.from_buffers(
    bad.schema.field(i).type,
    bad.num_rows,
    [None, pa.py_buffer(offsets.tobytes())],
    children=[bad.column(i).values],
  )
  bad = bad.set_column(i, bad.schema.field(i), damaged)
  path.write_bytes(data[:end] + bad.serialize().to_pybytes())
  read = _read_in_child(directory)
  assert read['episodes'] == [[0, 81], [1, 81], [2, 81], [3, 5]]
  (message,) = read['warnings']
  assert message.startswith(f'{path} is damaged or cut short after 5 rows')
  assert 'out of bounds' in message and 'read up to there' in message
  (episode,) = [e for e in _read(directory)[0] if len(e) == 5]
  _assert_equal_steps(episode.steps, episodes[3].steps, 5)


@pytest.mark.slow
def test_a_changed_value_in_a_finished_file_is_found_by_its_checksum(copy):
  # A valid Parquet file with another reward: the file's checks cannot
  # know, its SHA-256 in episodes.jsonl does.
  directory, _ = copy
  path = _path(directory, 1, 'parquet')
  table = pq.read_table(path)
  rewards = table.column('next.reward').to_pylist()
  rewards[40] += 1.0
  table = table.set_column(
    table.schema.get_field_index('next.reward'),
    'next.reward',
    pa.array(rewards, pa.float64()),
  )
  pq.write_table(table, path, write_page_checksum=True)
  episodes, messages = _read(directory)
  assert [e.metadata['episode_index'] for e in episodes] == [0, 2, 3]
  (message,) = messages
  assert str(path) in message and 'episode 1 skipped' in message
  assert 'SHA-256' in message


def test_a_changed_value_in_a_stream_is_found_by_its_checksum(copy):
  # One bit of row 6's wall-clock time: the batch's CRC-32 differs, so
  # the rows before it are read and the rest named.
  directory, episodes = copy
  path = _path(directory, 3, 'arrows')
  data = bytearray(path.read_bytes())
  value = struct.pack('<d', episodes[3].steps['wall_time'][6])
  assert data.count(value) == 1
  data[data.index(value)] ^= 1  # The lowest bit of the mantissa.
  path.write_bytes(bytes(data))
  read, messages = _read(directory)
  assert [len(e) for e in read] == [81, 81, 81, 6]
  (message,) = messages
  assert message.startswith(f'{path} is damaged or cut short after 6 rows')
  assert 'rows 6 to 6 do not match their checksum' in message
  _assert_equal_steps(read[3].steps, episodes[3].steps, 6)


@pytest.mark.slow
def test_random_bit_flips_in_both_robots_files_are_named_or_harmless(
  monkeypatch, tmp_path
):
  # Each flip: a warning names the file and only undamaged rows are read,
  # or nothing changed (padding, unused bytes); the reading runs in a
  # child process, so a crash is reported with its flip.
  monkeypatch.syspath_prepend(str(_BENCHMARKS))
  damage = importlib.import_module('recording_damage')
  robots = ['dclaw', 'dkitty']
  result = damage.run(flips=360, seed=0, robots=robots, directory=tmp_path)
  assert result['failures'] == []
  counts = result['counts']
  assert sorted(counts) == sorted(
    f'{robot} {kind}' for robot in robots for kind in damage.KINDS
  )
  assert all(sum(c.values()) == 60 for c in counts.values()), counts
  # With its episodes.jsonl line, a finished file's every flip is found.
  assert counts['dclaw parquet'] == counts['dkitty parquet'] == {'named': 60}
