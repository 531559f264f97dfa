"""Recordings after a kill at each write phase, damaged files, the timer
flush, fsync, a directory bound to one task, and the summary's safety."""

import json
import os
import pathlib
import subprocess
import sys
import threading
import time
import warnings

import numpy as np
import pytest

pytest.importorskip('pyarrow', reason='needs robel_dm[data]')

from robel_dm import evaluation, recording, suite  # noqa: E402
from robel_dm.recording import format as format_lib  # noqa: E402
from robel_dm.tasks import base  # noqa: E402

ROWS = 81  # A dclaw/pose_fixed episode: the reset's row and 80 steps.
SESSION = {'domain': 'dclaw', 'task': 'pose_fixed', 'policy': 'zero'}

# The child records episode 0 to its end, then patches the next operation of
# the phase to kill the process (os._exit(9): no cleanup, no flush, as
# kill -9) and records episode 1 into it.
CHILD = """
import builtins, os, pathlib, sys, time
import numpy as np
from robel_dm import recording, suite
from robel_dm.recording import format as format_lib

directory, phase = pathlib.Path(sys.argv[1]), sys.argv[2]
env = recording.Recorder(
  suite.load('dclaw', 'pose_fixed', seed=0), directory,
  metadata={session!r},
)


def episode():
  timestep = env.reset()
  while not timestep.last():
    timestep = env.step(np.zeros(9))


def die(*args, **kwargs):
  os._exit(9)


episode()  # Finished before the kill.
if phase == 'stream':  # Mid-episode, just after a flush reached the file.
  flush = format_lib.EpisodeWriter.flush

  def flush_then_die(self):
    flush(self)
    if self.stream_path.exists():
      print(self.length, flush=True)
      os._exit(9)

  format_lib.EpisodeWriter.flush = flush_then_die
  env.reset()
  for _ in range(5):
    env.step(np.zeros(9))
  time.sleep(30)  # A stalled loop: the timer flushes.
elif phase == 'partial':  # The Parquet file written, before the rename.
  os.replace = die
elif phase == 'renamed':  # Renamed, before the stream is unlinked.
  pathlib.Path.unlink = die
elif phase == 'unlinked':  # Stream unlinked, before the episodes.jsonl line.
  builtins_open = builtins.open

  def open_or_die(file, *args, **kwargs):
    if str(file).endswith('episodes.jsonl'):
      os._exit(9)
    return builtins_open(file, *args, **kwargs)

  builtins.open = open_or_die
episode()
print('not killed', flush=True)
"""


def _killed_child(directory: pathlib.Path, phase: str) -> str:
  result = subprocess.run(
    [sys.executable, '-c', CHILD.format(session=SESSION), str(directory),
     phase],
    capture_output=True, text=True, timeout=120, check=False,
  )  # fmt: skip
  assert result.returncode == 9, result.stderr
  return result.stdout


def _read(directory) -> tuple[list[recording.Episode], list[str]]:
  """The episodes, and the messages of the warnings reading them gave."""
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter('always')
    episodes = recording.read(directory)
  return episodes, [str(w.message) for w in caught]


def _record(directory, policy: str, episodes: int = 1) -> None:
  env = recording.Recorder(
    suite.load('dclaw', 'pose_fixed', seed=0),
    directory,
    metadata={**SESSION, 'policy': policy},
  )
  rng = np.random.default_rng(0)
  try:
    for _ in range(episodes):
      timestep = env.reset()
      while not timestep.last():
        timestep = env.step(rng.uniform(-1, 1, 9))
  finally:
    env.close()


def _files(directory: pathlib.Path) -> list[str]:
  return sorted(p.name for p in (directory / format_lib.CHUNK).iterdir())


# Phase -> the files it leaves, and the warning reading them gives.
PHASES = {
  'stream': (['episode_000000.parquet', 'episode_000001.arrows'], None),
  'partial': (
    ['episode_000000.parquet', 'episode_000001.arrows',
     'episode_000001.parquet.partial'],
    'episode_000001.parquet.partial is an unfinished Parquet file',
  ),
  'renamed': (
    ['episode_000000.parquet', 'episode_000001.arrows',
     'episode_000001.parquet'],
    None,
  ),
  'unlinked': (['episode_000000.parquet', 'episode_000001.parquet'], None),
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize('phase', list(PHASES))
def test_a_kill_at_each_write_phase_loses_no_finished_episode(tmp_path, phase):
  output = _killed_child(tmp_path, phase)
  files, warning = PHASES[phase]
  assert _files(tmp_path) == files
  episodes, messages = _read(tmp_path)
  assert messages == ([] if warning is None else [messages[0]])
  if warning is not None:
    assert warning in messages[0] and str(tmp_path) in messages[0]
  # The finished episode once, complete; the interrupted one once, not.
  assert [e.metadata['episode_index'] for e in episodes] == [0, 1]
  finished, interrupted = episodes
  assert finished.metadata['complete'] is True and len(finished) == ROWS
  assert interrupted.metadata['complete'] is False
  # Cut mid-episode: the rows the flush wrote (the reset's and 5 steps).
  rows = 6 if phase == 'stream' else ROWS
  assert output.split() == (['6'] if phase == 'stream' else [])
  assert len(interrupted) == interrupted.metadata['length'] == rows
  assert list(interrupted.steps['frame_index']) == list(range(rows))
  assert set(interrupted.steps['episode_index']) == {1}
  assert interrupted.metadata['policy'] == 'zero'
  assert interrupted.metadata['task'] == 'pose_fixed'
  # Another session appends after it; the crashed episode keeps its own
  # metadata though info.json now holds the new session's.
  _record(tmp_path, policy='random')
  episodes, messages = _read(tmp_path)
  assert messages == ([] if warning is None else [messages[0]])
  assert [e.metadata['episode_index'] for e in episodes] == [0, 1, 2]
  assert [e.metadata['complete'] for e in episodes] == [True, False, True]
  assert [e.metadata['policy'] for e in episodes] == ['zero', 'zero', 'random']
  assert [len(e) for e in episodes] == [ROWS, rows, ROWS]
  info = json.loads((tmp_path / format_lib.INFO).read_text())
  assert info['session']['policy'] == 'random'


def test_next_index_counts_unfinished_parquet_files(tmp_path):
  format_lib.prepare(tmp_path)
  (tmp_path / format_lib.CHUNK / 'episode_000004.parquet.partial').touch()
  (tmp_path / format_lib.CHUNK / 'episode_000002.arrows').touch()
  (tmp_path / format_lib.CHUNK / 'notes.txt').touch()
  assert format_lib.next_index(tmp_path) == 5


@pytest.mark.slow
def test_a_truncated_parquet_file_costs_only_its_episode(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 3, policy='zero', record=tmp_path
    )
  )
  path = tmp_path / format_lib.CHUNK / 'episode_000001.parquet'
  data = path.read_bytes()
  path.write_bytes(data[: len(data) // 2])
  episodes, messages = _read(tmp_path)
  assert [e.metadata['episode_index'] for e in episodes] == [0, 2]
  assert all(e.metadata['complete'] and len(e) == ROWS for e in episodes)
  assert len(messages) == 1
  assert str(path) in messages[0] and 'unreadable' in messages[0]
  # The summary and the next session go on past it.
  with pytest.warns(UserWarning, match='episode_000001.parquet'):
    summary = recording.summarize(tmp_path)
  assert [r['episode'] for r in summary] == [0, 2]
  _record(tmp_path, policy='random')
  episodes, _ = _read(tmp_path)
  assert [e.metadata['episode_index'] for e in episodes] == [0, 2, 3]


@pytest.mark.slow
def test_an_unreadable_parquet_file_falls_back_to_its_stream(tmp_path):
  # A kill after the rename left both files; then the Parquet file is
  # damaged: the episode is read from the stream.
  _killed_child(tmp_path, 'renamed')
  path = tmp_path / format_lib.CHUNK / 'episode_000001.parquet'
  path.write_bytes(path.read_bytes()[:100])
  episodes, messages = _read(tmp_path)
  assert [e.metadata['episode_index'] for e in episodes] == [0, 1]
  assert len(episodes[1]) == ROWS and episodes[1].metadata['policy'] == 'zero'
  assert len(messages) == 1 and 'read from its stream' in messages[0]


@pytest.mark.slow
def test_a_torn_episodes_line_costs_only_its_episode(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 2, policy='zero', record=tmp_path
    )
  )
  path = tmp_path / format_lib.EPISODES
  text = path.read_text()
  first, second = text.splitlines()
  path.write_text(first + '\n' + second[: len(second) // 2])  # Torn.
  episodes, messages = _read(tmp_path)
  assert len(messages) == 1
  assert str(path) in messages[0] and 'line 2' in messages[0]
  assert [e.metadata['episode_index'] for e in episodes] == [0, 1]
  assert episodes[0].metadata == json.loads(first)
  # Its data is whole; without its line it is not known to be complete.
  assert len(episodes[1]) == ROWS
  assert episodes[1].metadata['complete'] is False
  assert episodes[1].metadata['policy'] == 'zero'
  # The next line starts on a line of its own, readable.
  _record(tmp_path, policy='random')
  episodes, messages = _read(tmp_path)
  assert len(messages) == 1 and 'line 2' in messages[0]
  assert [e.metadata['complete'] for e in episodes] == [True, False, True]
  assert episodes[2].metadata['policy'] == 'random'


def _flush_threads() -> list[threading.Thread]:
  return [
    t
    for t in threading.enumerate()
    if t.name.startswith('recording-flush') and t.is_alive()
  ]


@pytest.mark.slow
def test_a_stalled_loop_still_reaches_the_disk(tmp_path):
  env = recording.Recorder(suite.load('dclaw', 'pose_fixed', seed=0), tmp_path)
  try:
    env.reset()
    for _ in range(3):
      env.step(np.zeros(9))
    # No further step: the rows must still reach the stream file.
    stream = tmp_path / format_lib.CHUNK / 'episode_000000.arrows'
    stalled = time.monotonic()
    rows = 0
    while time.monotonic() - stalled < 3 and rows < 4:
      time.sleep(0.05)
      if stream.exists() and stream.stat().st_size:
        (episode,) = recording.read(tmp_path)
        rows = len(episode)
    assert rows == 4, f'{rows} of 4 rows on disk after 3 s without a step'
    assert len(_flush_threads()) == 1
  finally:
    env.close()
  assert not _flush_threads()  # close() stops the timer.
  (episode,) = recording.read(tmp_path)
  assert len(episode) == 4 and episode.metadata['complete'] is False


@pytest.mark.slow
def test_every_write_the_guarantee_needs_is_fsynced(tmp_path, monkeypatch):
  if not os.path.isdir('/proc/self/fd'):
    pytest.skip('names a descriptor through /proc')
  synced = []
  fsync = os.fsync

  def recording_fsync(descriptor):
    synced.append(os.readlink(f'/proc/self/fd/{descriptor}'))
    fsync(descriptor)

  monkeypatch.setattr(os, 'fsync', recording_fsync)
  monkeypatch.setattr(format_lib, 'FLUSH_INTERVAL', 1e-9)  # Every row.
  _record(tmp_path, policy='zero')
  chunk = str((tmp_path / format_lib.CHUNK).resolve())
  stream = f'{chunk}/episode_000000.arrows'
  assert synced.count(stream) == ROWS  # After every flush.
  assert f'{chunk}/episode_000000.parquet.partial' in synced
  # The new stream, the rename, the unlink.
  assert synced.count(chunk) == 3
  # The new directories' entries: data/chunk-000, data and meta, the
  # recording directory itself.
  root = tmp_path.resolve()
  for directory in (root / 'data', root, root.parent):
    assert str(directory) in synced, directory
  assert str((tmp_path / format_lib.EPISODES).resolve()) in synced
  assert str((tmp_path / format_lib.INFO).resolve()) + '.partial' in synced
  # And none with the switch off.
  synced.clear()
  monkeypatch.setattr(format_lib, 'FSYNC', False)
  _record(tmp_path, policy='zero')
  assert synced == []


@pytest.mark.slow
def test_a_directory_of_another_task_is_refused_untouched(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 1, policy='zero', record=tmp_path
    )
  )
  info = (tmp_path / format_lib.INFO).read_bytes()
  files = sorted(str(p) for p in tmp_path.rglob('*'))
  cases = [
    ('turn_fixed', {'domain': 'dclaw', 'task': 'turn_fixed'}),
    ('pose_fixed', {**SESSION, 'task_kwargs': {'observation_noise': 0.1}}),
    ('turn_fixed', None),  # No metadata: its observation keys differ.
  ]
  for task, metadata in cases:
    env = suite.load('dclaw', task, seed=0)
    try:
      with pytest.raises(recording.RecordingError) as raised:
        recording.Recorder(env, tmp_path, metadata=metadata)
    finally:
      env.close()
    message = str(raised.value)
    assert '\n' not in message and str(tmp_path) in message
    assert 'pose_fixed' in message or 'qpos_error' in message
    assert task in message or 'claw_qpos' in message
  assert (tmp_path / format_lib.INFO).read_bytes() == info
  assert sorted(str(p) for p in tmp_path.rglob('*')) == files
  # The same task appends.
  _record(tmp_path, policy='random')
  assert len(recording.read(tmp_path)) == 2


@pytest.mark.slow
def test_the_summary_counts_safety_after_the_reset_as_evaluate(tmp_path):
  # D'Claw Turn starts with joints near their limits: the reset's row has
  # position violations, the steps after it none.
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'turn_fixed', 2, policy='zero', seed=0, record=tmp_path
    )
  )
  episodes = recording.read(tmp_path)
  assert all(e.steps['observation.safety'][0].any() for e in episodes)
  rows = recording.summarize(tmp_path)
  for row, record in zip(rows, results['records'], strict=True):
    assert row['safety'] == [record['safety'][f] for f in base.SAFETY_FIELDS]
  command = [sys.executable, '-m', 'robel_dm.commands.recording', str(tmp_path)]
  result = subprocess.run(command, capture_output=True, text=True, check=False)
  assert result.returncode == 0, result.stderr
  assert result.stdout.splitlines()[1].split()[-1] == '0/0/0'
