"""Recordings exported as LeRobotDatasets (v2.1): the files, the metadata,
and the frame convention (frame t: an observation, the action taken from
it, and what followed), checked against a fresh simulation."""

import json
import subprocess
import sys

import numpy as np
import pytest

pa = pytest.importorskip('pyarrow')

import pyarrow.dataset  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

from robel_dm import evaluate, recording, suite  # noqa: E402
from robel_dm.recording import lerobot  # noqa: E402

# What LeRobot 2.1's metadata loader reads from meta/info.json.
INFO_KEYS = {
  'codebase_version', 'robot_type', 'total_episodes', 'total_frames',
  'total_tasks', 'total_videos', 'total_chunks', 'chunks_size', 'fps',
  'splits', 'data_path', 'video_path', 'features',
}  # fmt: skip
# LeRobot's check_timestamps_sync tolerance, s.
TIMESTAMP_TOLERANCE = 1e-4


@pytest.fixture(scope='module')
def dataset(tmp_path_factory):
  root = tmp_path_factory.mktemp('export')
  evaluate.evaluate(
    'dclaw', 'pose_fixed', 2, policy='random', seed=7, record=root / 'rec'
  )
  # An episode cut short: recorded, but not exported.
  env = recording.Recorder(suite.load('dclaw', 'pose_fixed'), root / 'rec')
  env.reset()
  env.step(np.zeros(9))
  env.close()
  info = lerobot.export(root / 'rec', root / 'out')
  return root / 'out', info


def _lines(path):
  return [json.loads(line) for line in path.read_text().splitlines()]


def test_metadata_follows_lerobot_v2_1(dataset):
  out, info = dataset
  assert json.loads((out / 'meta/info.json').read_text()) == info
  assert set(info) >= INFO_KEYS
  assert info['codebase_version'] == 'v2.1'
  assert info['fps'] == 20 and isinstance(info['fps'], int)
  assert info['total_episodes'] == 2 and info['splits'] == {'train': '0:2'}
  episodes = _lines(out / 'meta/episodes.jsonl')
  assert [e['episode_index'] for e in episodes] == [0, 1]
  assert [e['tasks'] for e in episodes] == [['dclaw/pose_fixed']] * 2
  assert sum(e['length'] for e in episodes) == info['total_frames']
  assert _lines(out / 'meta/tasks.jsonl') == [
    {'task_index': 0, 'task': 'dclaw/pose_fixed'}
  ]
  for name in lerobot.INDEX_COLUMNS + ('observation.state', 'action'):
    assert name in info['features']
  assert info['features']['observation.state']['shape'] == [27]
  assert info['features']['action'] == {
    'dtype': 'float64', 'shape': [9], 'names': None
  }  # fmt: skip


def test_data_files_match_the_features(dataset):
  out, info = dataset
  features = info['features']
  index = 0
  for episode in _lines(out / 'meta/episodes.jsonl'):
    path = out / info['data_path'].format(
      episode_chunk=episode['episode_index'] // info['chunks_size'],
      episode_index=episode['episode_index'],
    )
    table = pq.read_table(path)
    assert set(table.column_names) == set(features)
    assert table.num_rows == episode['length']
    for name, feature in features.items():
      values = np.array(table.column(name).to_pylist())
      kind = {'float64': 'f', 'int64': 'i', 'bool': 'b'}[feature['dtype']]
      assert values.dtype.kind == kind, name
      shape = [1] if values.ndim == 1 else list(values.shape[1:])
      assert shape == feature['shape'], name
    assert table.column('frame_index').to_pylist() == list(
      range(episode['length'])
    )
    assert table.column('index').to_pylist() == list(
      range(index, index + episode['length'])
    )
    index += episode['length']
    gaps = np.diff(table.column('timestamp').to_numpy())
    assert np.all(np.abs(gaps - 1 / info['fps']) < TIMESTAMP_TOLERANCE)
  # The whole data directory reads as one table (as Hugging Face datasets
  # loads it), every frame once.
  whole = pyarrow.dataset.dataset(out / 'data', format='parquet').to_table()
  assert sorted(whole.column('index').to_pylist()) == list(
    range(info['total_frames'])
  )


def test_frames_are_observation_then_action_taken(dataset):
  out, info = dataset
  env = suite.load('dclaw', 'pose_fixed', seed=7)
  for episode in _lines(out / 'meta/episodes.jsonl'):
    path = out / info['data_path'].format(
      episode_chunk=0, episode_index=episode['episode_index']
    )
    frames = {
      k: np.array(v) for k, v in pq.read_table(path).to_pydict().items()
    }
    timestep = env.reset()
    for t in range(episode['length']):
      np.testing.assert_array_equal(
        frames['observation.state'][t],
        env.task.flatten_observation(timestep.observation),
      )
      timestep = env.step(frames['action'][t])
      assert frames['next.reward'][t] == timestep.reward
      assert frames['next.done'][t] == timestep.last()
    assert timestep.last()
  env.close()


def test_episode_stats_describe_the_frames(dataset):
  out, info = dataset
  (first, _) = _lines(out / 'meta/episodes_stats.jsonl')
  path = out / info['data_path'].format(episode_chunk=0, episode_index=0)
  actions = np.array(pq.read_table(path).column('action').to_pylist())
  stats = first['stats']['action']
  np.testing.assert_allclose(stats['mean'], actions.mean(axis=0))
  np.testing.assert_allclose(stats['min'], actions.min(axis=0))
  assert stats['count'] == [len(actions)]
  assert set(first['stats']) == set(info['features'])


def test_command_line_export_and_its_errors(dataset, tmp_path):
  out, _ = dataset
  recording_dir = out.parent / 'rec'
  command = [sys.executable, '-m', 'robel_dm.recording', str(recording_dir)]
  done = subprocess.run(
    [*command, f'--lerobot={tmp_path / "again"}'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert done.returncode == 0, done.stderr
  assert 'wrote' in done.stdout and '2 episodes' in done.stdout
  again = subprocess.run(
    [*command, f'--lerobot={tmp_path / "again"}'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert again.returncode == 2 and 'exists' in again.stderr
