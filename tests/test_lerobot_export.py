"""Recordings exported as LeRobotDatasets (v3.0, the default, and v2.1):
the files, the metadata, and the frame convention (frame t: an observation,
the action taken from it, and what followed), checked against the format's
rules and a fresh simulation. (Loading with LeRobot itself needs another
torch than the `learn` extra: tests/external/load_with_lerobot.py, run by
hand, docs/recording.md.)"""

import json
import subprocess
import sys

import numpy as np
import pytest

pa = pytest.importorskip('pyarrow', reason='needs robel_dm[data]')

import pyarrow.dataset  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

from robel_dm import evaluation, recording, suite  # noqa: E402
from robel_dm.recording import lerobot  # noqa: E402

# What LeRobot 2.1's metadata loader reads from meta/info.json.
INFO_KEYS = {
  'codebase_version', 'robot_type', 'total_episodes', 'total_frames',
  'total_tasks', 'total_videos', 'total_chunks', 'chunks_size', 'fps',
  'splits', 'data_path', 'video_path', 'features',
}  # fmt: skip
# LeRobot 3.0's DatasetInfo: every key it knows (it warns about others).
INFO_KEYS_V30 = {
  'codebase_version', 'fps', 'features', 'total_episodes', 'total_frames',
  'total_tasks', 'chunks_size', 'data_files_size_in_mb',
  'video_files_size_in_mb', 'data_path', 'video_path', 'robot_type',
  'splits',
}  # fmt: skip
# What LeRobot 3.0 reads from each row of meta/episodes/.
EPISODE_KEYS_V30 = {
  'episode_index', 'tasks', 'length', 'data/chunk_index', 'data/file_index',
  'dataset_from_index', 'dataset_to_index', 'meta/episodes/chunk_index',
  'meta/episodes/file_index',
}  # fmt: skip
# LeRobot's check_timestamps_sync tolerance, s.
TIMESTAMP_TOLERANCE = 1e-4


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
  root = tmp_path_factory.mktemp('export')
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 2, policy='random', seed=7, record=root / 'rec'
    )
  )
  # An episode cut short: recorded, but not exported.
  env = recording.Recorder(suite.load('dclaw', 'pose_fixed'), root / 'rec')
  env.reset()
  env.step(np.zeros(9))
  env.close()
  return root / 'rec'


@pytest.fixture(scope='module')
def dataset(recorded):
  info = lerobot.export(recorded, recorded.parent / 'v21', version='v2.1')
  return recorded.parent / 'v21', info


@pytest.fixture(scope='module')
def dataset_v30(recorded):
  info = lerobot.export(recorded, recorded.parent / 'v30')
  return recorded.parent / 'v30', info


def _lines(path):
  return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.slow
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
  joints = ['FFJ10', 'FFJ11', 'FFJ12', 'MFJ20', 'MFJ21', 'MFJ22', 'THJ30',
            'THJ31', 'THJ32']  # fmt: skip
  assert info['features']['action'] == {
    'dtype': 'float64', 'shape': [9], 'names': joints
  }  # fmt: skip
  # The agent's vector names each dimension by the observation it is from.
  names = info['features']['observation.state']['names']
  assert names[:9] == [f'qpos.{joint}' for joint in joints]
  assert names[9:18] == [f'last_action.{joint}' for joint in joints]


@pytest.mark.slow
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


@pytest.mark.slow
def test_command_line_export_and_its_errors(dataset, tmp_path):
  out, _ = dataset
  recording_dir = out.parent / 'rec'
  command = [
    sys.executable,
    '-m',
    'robel_dm.commands.recording',
    str(recording_dir),
  ]
  done = subprocess.run(
    [*command, f'--lerobot={tmp_path / "again"}'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert done.returncode == 0, done.stderr
  assert 'wrote' in done.stdout and '2 episodes' in done.stdout
  assert 'v3.0' in done.stdout  # The default.
  old = subprocess.run(
    [*command, f'--lerobot={tmp_path / "old"}', '--lerobot_version=v2.1'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert old.returncode == 0 and 'v2.1' in old.stdout, old.stderr
  again = subprocess.run(
    [*command, f'--lerobot={tmp_path / "again"}'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert again.returncode == 2 and 'exists' in again.stderr


def _v30_frames(out, info):
  """Every data file of a v3.0 dataset, as one table."""
  return pyarrow.dataset.dataset(out / 'data', format='parquet').to_table()


def test_v30_metadata_is_what_lerobot_3_reads(dataset_v30):
  out, info = dataset_v30
  assert json.loads((out / 'meta/info.json').read_text()) == info
  assert set(info) == INFO_KEYS_V30
  assert info['codebase_version'] == 'v3.0'
  assert info['fps'] == 20 and isinstance(info['fps'], int)
  assert info['total_episodes'] == 2 and info['splits'] == {'train': '0:2'}
  assert info['data_path'] == (
    'data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet'
  )
  for name, feature in info['features'].items():
    assert '/' not in name  # LeRobot refuses such feature names.
    assert set(feature) == {'dtype', 'shape', 'names', 'fps'}
    assert feature['fps'] == info['fps']
  provenance = json.loads((out / lerobot.ROBEL_DM_META).read_text())
  assert provenance['columns']['observation.qpos']['unit'] == 'rad'


def test_v30_episodes_point_at_their_frames(dataset_v30):
  out, info = dataset_v30
  episodes = pq.read_table(out / 'meta/episodes/chunk-000/file-000.parquet')
  assert set(episodes.column_names) >= EPISODE_KEYS_V30
  rows = episodes.to_pylist()
  assert [r['episode_index'] for r in rows] == [0, 1]
  assert sum(r['length'] for r in rows) == info['total_frames']
  for row in rows:
    assert row['tasks'] == ['dclaw/pose_fixed']
    path = out / info['data_path'].format(
      chunk_index=row['data/chunk_index'], file_index=row['data/file_index']
    )
    table = pq.read_table(path).to_pydict()
    mine = [
      i for i, e in zip(table['index'], table['episode_index'], strict=True)
      if e == row['episode_index']
    ]  # fmt: skip
    assert mine == list(range(row['dataset_from_index'],
                              row['dataset_to_index']))  # fmt: skip
    assert len(mine) == row['length']
    for name in info['features']:
      assert f'stats/{name}/mean' in row, name
  whole = _v30_frames(out, info)
  assert sorted(whole.column('index').to_pylist()) == list(
    range(info['total_frames'])
  )
  frame_index = np.array(whole.column('frame_index').to_pylist())
  gaps = np.diff(np.array(whole.column('timestamp').to_pylist()))
  within = np.diff(frame_index) == 1
  assert np.all(np.abs(gaps[within] - 1 / info['fps']) < TIMESTAMP_TOLERANCE)


def test_v30_scalars_are_scalars_and_times_are_float64(dataset_v30, recorded):
  out, info = dataset_v30
  schema = pq.read_schema(next((out / 'data').glob('*/*.parquet')))
  for name, feature in info['features'].items():
    arrow = schema.field(name).type
    if feature['shape'] == [1]:
      # LeRobot reads a [1] feature as a scalar: a one-element list breaks it.
      assert not pa.types.is_list(arrow), name
    else:
      assert pa.types.is_list(arrow), name
  for name in ('timestamp', 'wall_time_elapsed'):
    assert info['features'][name]['dtype'] == 'float64'
    assert schema.field(name).type == pa.float64()
  # Wall-clock times are kept, as an offset from the episode's start (small
  # enough to survive the float32 LeRobot hands to torch) and that start.
  episode = recording.read(recorded)[0]
  whole = _v30_frames(out, info).to_pydict()
  elapsed = [
    t
    for t, e in zip(
      whole['wall_time_elapsed'], whole['episode_index'], strict=True
    )
    if e == 0
  ]
  episodes = pq.read_table(out / 'meta/episodes/chunk-000/file-000.parquet')
  start = episodes.column('wall_time_start').to_pylist()[0]
  assert start == episode.steps['wall_time'][0]
  assert elapsed[0] == 0.0 and np.all(np.diff(elapsed) > 0)
  np.testing.assert_allclose(
    start + np.array(elapsed), episode.steps['wall_time'][:-1], rtol=0,
    atol=1e-6,
  )  # fmt: skip
  assert len(set(np.float32(elapsed))) == len(elapsed)


def test_v30_tasks_and_stats(dataset_v30):
  out, info = dataset_v30
  tasks = pq.read_table(out / 'meta/tasks.parquet')
  # pandas (as LeRobot reads it) takes the task text as the frame's index.
  pandas_meta = json.loads(tasks.schema.metadata[b'pandas'])
  [index] = pandas_meta['index_columns']
  assert tasks.column(index).to_pylist() == ['dclaw/pose_fixed']
  assert tasks.column('task_index').to_pylist() == [0]
  stats = json.loads((out / 'meta/stats.json').read_text())
  assert set(stats) == set(info['features'])
  actions = np.array(_v30_frames(out, info).column('action').to_pylist())
  np.testing.assert_allclose(stats['action']['mean'], actions.mean(axis=0))
  np.testing.assert_allclose(stats['action']['max'], actions.max(axis=0))
  assert stats['action']['count'] == [info['total_frames']]


@pytest.mark.slow
def test_v30_frames_are_observation_then_action_taken(dataset_v30):
  out, info = dataset_v30
  whole = {
    k: np.array(v) for k, v in _v30_frames(out, info).to_pydict().items()
  }
  env = suite.load('dclaw', 'pose_fixed', seed=7)
  for episode_index in range(info['total_episodes']):
    rows = np.flatnonzero(whole['episode_index'] == episode_index)
    rows = rows[np.argsort(whole['frame_index'][rows])]
    timestep = env.reset()
    for row in rows:
      np.testing.assert_array_equal(
        whole['observation.state'][row],
        env.task.flatten_observation(timestep.observation),
      )
      timestep = env.step(whole['action'][row])
      assert whole['next.reward'][row] == timestep.reward
    assert timestep.last()
  env.close()


def test_export_refuses_an_unknown_version(recorded, tmp_path):
  with pytest.raises(ValueError, match='v3.0 or v2.1'):
    lerobot.export(recorded, tmp_path / 'x', version='v4')
  assert not (tmp_path / 'x').exists()


def test_export_refuses_a_missing_folder_and_leaves_nothing_on_failure(
  recorded, tmp_path, monkeypatch
):
  with pytest.raises(recording.RecordingError, match='no folder'):
    lerobot.export(recorded, tmp_path / 'typo' / 'out')
  assert not (tmp_path / 'typo').exists()  # Not created on the way.

  def disk_full(*args, **kwargs):
    raise OSError(28, 'No space left on device')

  monkeypatch.setattr(lerobot, '_dataset_info', disk_full)
  with pytest.raises(recording.RecordingError, match='writing .* No space'):
    lerobot.export(recorded, tmp_path / 'out')
  assert list(tmp_path.iterdir()) == []  # No dataset, no staging folder.


@pytest.mark.slow
@pytest.mark.parametrize(
  'domain, task', [('dclaw', 'turn_fixed'), ('dkitty', 'walk_fixed')]
)
def test_each_state_name_locates_its_dimension(tmp_path, domain, task):
  # Names such as FFJ10 (in claw_qpos and last_action) or x (in root_pos,
  # root_euler, root_vel ...) repeated over the vector.
  evaluation.evaluate(
    evaluation.EvalConfig(
      domain, task, 1, policy='zero', record=tmp_path / 'rec'
    )
  )
  info = lerobot.export(tmp_path / 'rec', tmp_path / 'out')
  features = info['features']
  names = features['observation.state']['names']
  assert (
    len(set(names)) == len(names) == features['observation.state']['shape'][0]
  )
  frames = {
    k: np.array(v)
    for k, v in _v30_frames(tmp_path / 'out', info).to_pydict().items()
  }
  for i, name in enumerate(names):
    key, _, dimension = name.partition('.')
    values = frames[f'observation.{key}']
    if dimension:
      values = values[
        :, features[f'observation.{key}']['names'].index(dimension)
      ]
    else:
      assert values.ndim == 1, name
    np.testing.assert_array_equal(frames['observation.state'][:, i], values)


def test_exported_episodes_keep_their_recording_index_and_seed(
  dataset, dataset_v30
):
  # The recording's episodes 0 and 1, reset with seeds 7 and 8 (its
  # episode 2 was cut short and is not exported).
  expected = [(0, 7), (1, 8)]
  out, _ = dataset
  lines = _lines(out / 'meta/episodes.jsonl')
  assert [
    (e['recording_episode_index'], e['episode_seed']) for e in lines
  ] == expected
  out, _ = dataset_v30
  rows = pq.read_table(
    out / 'meta/episodes/chunk-000/file-000.parquet'
  ).to_pylist()
  assert [
    (r['recording_episode_index'], r['episode_seed']) for r in rows
  ] == expected


@pytest.mark.slow
def test_an_episode_without_a_seed_keeps_its_index(tmp_path):
  # A Recorder used without evaluate records no episode_seed: after one
  # that has it, its row says None (and the seed is not dropped).
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 1, policy='zero', seed=7, record=tmp_path / 'rec'
    )
  )
  env = recording.Recorder(
    suite.load('dclaw', 'pose_fixed', time_limit=0.5),
    tmp_path / 'rec',
    metadata={'domain': 'dclaw', 'task': 'pose_fixed'},
  )
  timestep = env.reset()
  while not timestep.last():
    timestep = env.step(np.zeros(9))
  env.close()
  lerobot.export(tmp_path / 'rec', tmp_path / 'out')
  rows = pq.read_table(
    tmp_path / 'out/meta/episodes/chunk-000/file-000.parquet'
  ).to_pylist()
  assert [(r['recording_episode_index'], r['episode_seed']) for r in rows] == [
    (0, 7),
    (1, None),
  ]


@pytest.mark.slow
@pytest.mark.parametrize('version', lerobot.VERSIONS)
def test_motor_times_are_relative_to_the_episode(tmp_path, version):
  # time.monotonic() is the uptime: in float32 (LeRobot's tensors) it keeps
  # 6e-5 s after 10 minutes, 0.06 s after 10 days.
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  env = suite.load(
    'dclaw',
    'pose_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual'),
    time_limit=1.0,
  )
  env = recording.Recorder(
    env, tmp_path / 'rec', metadata={'domain': 'dclaw', 'task': 'pose_fixed'}
  )
  timestep = env.reset()
  while not timestep.last():
    timestep = env.step(np.zeros(9))
  env.close()
  (episode,) = recording.read(tmp_path / 'rec')
  info = lerobot.export(tmp_path / 'rec', tmp_path / 'out', version=version)
  if version == 'v3.0':
    frames = _v30_frames(tmp_path / 'out', info).to_pydict()
    (metadata,) = pq.read_table(
      tmp_path / 'out/meta/episodes/chunk-000/file-000.parquet'
    ).to_pylist()
  else:
    path = (
      tmp_path
      / 'out'
      / info['data_path'].format(episode_chunk=0, episode_index=0)
    )
    frames = pq.read_table(path).to_pydict()
    (metadata,) = _lines(tmp_path / 'out/meta/episodes.jsonl')
  # The origin: the episode's first motor read, the reset's health read.
  steps = episode.steps
  start = min(steps['motor.timestamp'][0], steps['motor.health_timestamp'][0])
  assert metadata['motor_time_start'] == start
  duration = steps['motor.timestamp'][-1] - start
  for name in ('motor.timestamp', 'motor.health_timestamp'):
    exported = np.array(frames[name])
    np.testing.assert_array_equal(exported, steps[name][1:] - start)
    assert np.all((exported >= 0) & (exported <= duration)), name
    # What LeRobot's float32 keeps of it: within a microsecond.
    restored = start + exported.astype(np.float32).astype(np.float64)
    np.testing.assert_allclose(restored, steps[name][1:], rtol=0, atol=1e-6)
  assert np.all(np.diff(frames['motor.timestamp']) > 0)
