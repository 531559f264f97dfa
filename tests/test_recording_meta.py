"""What a recording says about itself: replay refuses another seed, task or
task_kwargs than the recording's, and every Parquet file describes its own
columns (units, shapes, dimension names) without its directory; one
recorder at a time writes a directory."""

import json
import shutil
import subprocess
import sys

from absl import flags
import numpy as np
import pytest

pytest.importorskip('pyarrow', reason='needs robel_dm[data]')

from robel_dm import evaluation, policies, recording, suite  # noqa: E402
from robel_dm.evaluation import cli  # noqa: E402

FLAGS = flags.FLAGS
_TASK = ('dclaw', 'turn_random')
_SEED = 5
_CLAW_JOINTS = ['FFJ10', 'FFJ11', 'FFJ12', 'MFJ20', 'MFJ21', 'MFJ22',
                'THJ30', 'THJ31', 'THJ32']  # fmt: skip


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
  """A recording of 2 episodes of random actions, made with seed 5."""
  directory = tmp_path_factory.mktemp('recorded')
  evaluation.evaluate(
    evaluation.EvalConfig(
      *_TASK, 2, policy='random', seed=_SEED, record=directory
    )
  )
  return directory


def _steps(directory):
  return [e.steps for e in recording.read(directory)]


@pytest.mark.slow
def test_replay_from_the_recorded_seed_reproduces_the_episodes(
  recorded, tmp_path
):
  lines = (recorded / 'meta/episodes.jsonl').read_text().splitlines()
  assert [json.loads(line)['episode_seed'] for line in lines] == [5, 6]
  evaluation.evaluate(
    evaluation.EvalConfig(
      *_TASK, 2, policy=f'replay:{recorded}', seed=_SEED, record=tmp_path
    )
  )
  for first, again in zip(_steps(recorded), _steps(tmp_path), strict=True):
    for key in ('action', 'observation.claw_qpos', 'next.reward'):
      np.testing.assert_array_equal(first[key], again[key])


@pytest.mark.parametrize(
  'task, task_kwargs, seed, message',
  [
    ('turn_random', None, 6, 'was made with seed 5, not 6'),
    ('turn_random', None, None, 'was made with seed 5, not None'),
    ('turn_fixed', None, 5, 'is of dclaw/turn_random, not dclaw/turn_fixed'),
    ('turn_random', {'valve': 'valve4'}, 5,
     'was made with task_kwargs {}, not {"valve": "valve4"}'),
  ],
)  # fmt: skip
def test_replay_of_another_seed_or_task_is_refused_before_anything_is_built(
  recorded, built, task, task_kwargs, seed, message
):
  with pytest.raises(ValueError, match=message) as error:
    evaluation.evaluate(evaluation.EvalConfig(
      'dclaw', task, 1, policy=f'replay:{recorded}', seed=seed,
      task_kwargs=task_kwargs,
    ))  # fmt: skip
  assert str(recorded) in str(error.value)
  assert '\n' not in str(error.value)
  assert built == []  # Nothing built, so nothing stepped (or moved).


@pytest.mark.slow
def test_another_seed_replays_when_allowed(recorded, tmp_path):
  evaluation.evaluate(evaluation.EvalConfig(
    *_TASK, 1, policy=f'replay:{recorded}', seed=_SEED + 1,
    allow_other_seed=True, record=tmp_path,
  ))  # fmt: skip
  original, replayed = _steps(recorded)[0], _steps(tmp_path)[0]
  np.testing.assert_array_equal(original['action'], replayed['action'])
  assert not np.array_equal(
    original['observation.claw_qpos'], replayed['observation.claw_qpos']
  )  # Another start: the same actions give another episode.


@pytest.mark.slow
def test_each_replayed_episode_is_checked_against_its_own_reset(tmp_path):
  # Two sessions from seed 0 in one directory: both episodes were reset
  # with seed 0, where a replay from 0 resets the second with seed 1.
  for _ in range(2):
    evaluation.evaluate(
      evaluation.EvalConfig(*_TASK, 1, policy='zero', seed=0, record=tmp_path)
    )
  policies.ReplayPolicy(
    str(tmp_path), *_TASK, seed=0, episodes=1, check_seed=True
  )
  with pytest.raises(ValueError, match='episode 1 .* seed 0, not 0 \\+ 1'):
    evaluation.evaluate(
      evaluation.EvalConfig(*_TASK, 2, policy=f'replay:{tmp_path}', seed=0)
    )
  with pytest.raises(ValueError, match='has 2 episodes, not 3'):
    evaluation.evaluate(
      evaluation.EvalConfig(*_TASK, 3, policy=f'replay:{tmp_path}', seed=0)
    )


def _record_directly(directory, metadata) -> str:
  """A recording as a Recorder used without evaluate (or an older version,
  without episode_seed) leaves it: one short episode."""
  env = recording.Recorder(
    suite.load(*_TASK, seed=_SEED), directory, metadata=metadata
  )
  env.reset()
  env.step(np.zeros(9))
  env.close()
  return str(directory)


@pytest.mark.slow
def test_a_recording_that_does_not_say_replays(tmp_path):
  # Without a seed: any seed goes ahead.
  unsaid = _record_directly(tmp_path / 'a', {'domain': 'dclaw'})
  policies.ReplayPolicy(unsaid, *_TASK, seed=9, check_seed=True)
  # A session seed without the episodes' own (older recordings): compared.
  older = _record_directly(
    tmp_path / 'b', {'domain': _TASK[0], 'task': _TASK[1], 'seed': _SEED}
  )
  policies.ReplayPolicy(older, *_TASK, seed=_SEED, check_seed=True)
  with pytest.raises(ValueError, match='made with seed 5, not 7'):
    policies.ReplayPolicy(older, *_TASK, seed=7, check_seed=True)


@pytest.mark.slow
def test_a_cut_short_episode_is_refused_before_the_replay_starts(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(*_TASK, 1, policy='zero', seed=0, record=tmp_path)
  )
  _record_directly(tmp_path, {'domain': _TASK[0], 'task': _TASK[1]})
  # It used to fail mid-episode, after the first episode had run.
  with pytest.raises(ValueError, match='episode 1 .* cut short after 1 steps'):
    policies.ReplayPolicy(str(tmp_path), *_TASK, seed=0, episodes=2)
  policies.ReplayPolicy(str(tmp_path), *_TASK, seed=0, episodes=1)


def test_the_command_refuses_in_one_line_unless_allowed(
  recorded, built, evaluate_flags, capsys
):
  argv = ['evaluate', '--domain=dclaw', '--task=turn_random', '--seed=8',
          f'--policy=replay:{recorded}', '--episodes=1']  # fmt: skip
  try:
    FLAGS(argv)
    code = cli.main(['evaluate'])
    out, err = capsys.readouterr()
    assert code == 2 and not out and built == []
    assert err.strip().splitlines() == [
      f'error: the recording {recorded} was made with seed 5, not 8 '
      '(--allow_other_seed replays it anyway)'
    ]
    FLAGS.unparse_flags()
    FLAGS([*argv, '--allow_other_seed'])
    assert cli.main(['evaluate']) == 0
    assert 'success rate' in capsys.readouterr().out
  finally:
    FLAGS.unparse_flags()


def _lone_copy(directory, tmp_path):
  """Its first Parquet file, copied alone into an empty directory."""
  (source,) = (directory / 'data/chunk-000').glob('episode_000000.parquet')
  lone = tmp_path / 'elsewhere'
  lone.mkdir()
  shutil.copy(source, lone / 'copied.parquet')
  assert [p.name for p in lone.iterdir()] == ['copied.parquet']
  return lone / 'copied.parquet'


def test_a_parquet_file_alone_describes_its_columns(recorded, tmp_path):
  import pyarrow.parquet as pq  # noqa: PLC0415

  path = _lone_copy(recorded, tmp_path)
  description = recording.describe_columns(path)
  assert (description['domain'], description['task']) == _TASK
  assert description['task_kwargs'] == {} and description['fps'] == 10
  columns = description['columns']
  assert set(columns) == set(pq.read_schema(path).names)  # Every column.
  assert columns['observation.claw_qpos'] == {
    'unit': 'rad', 'shape': [9], 'names': _CLAW_JOINTS
  }  # fmt: skip
  assert columns['action'] == {'unit': '', 'shape': [9], 'names': _CLAW_JOINTS}
  assert columns['timestamp'] == {'unit': 's', 'shape': []}
  assert columns['joint_targets']['unit'] == 'rad'
  assert columns['observation.target_error']['unit'] == 'rad'
  assert columns['observation.safety']['names'] == [
    'position',
    'velocity',
    'current',
  ]
  assert columns['reward_terms.bonus_big'] == {'unit': '', 'shape': []}
  env = suite.load(*_TASK)
  assert [j.name for j in env.task.robot.joints] == _CLAW_JOINTS
  # The shapes are those of the stored rows.
  table = pq.read_table(path)
  assert len(table.column('observation.claw_qpos')[0]) == 9


def test_a_file_without_a_description_says_so(tmp_path):
  import pyarrow as pa  # noqa: PLC0415
  import pyarrow.parquet as pq  # noqa: PLC0415

  path = tmp_path / 'old.parquet'
  pq.write_table(pa.table({'timestamp': [0.0]}), str(path))
  with pytest.raises(recording.RecordingError, match='no description'):
    recording.describe_columns(path)


@pytest.mark.slow
def test_a_robot_recording_describes_its_motors(tmp_path):
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  env = suite.load(
    'dclaw', 'turn_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  motor_ids = list(env.robot.motor_ids)
  config = env.robot_config
  valve = config.auxiliary_motor('valve').id
  assert motor_ids == [*config.joint_ids, valve]
  env = recording.Recorder(env, tmp_path / 'rec')
  env.reset()
  env.step(np.zeros(9))
  env.close()
  description = recording.describe_columns(
    _lone_copy(tmp_path / 'rec', tmp_path)
  )
  columns = description['columns']
  assert columns['motor.current'] == {
    'unit': 'mA', 'shape': [len(motor_ids)], 'names': motor_ids
  }  # fmt: skip
  assert [columns[f'motor.{name}']['unit'] for name in (
    'position', 'velocity', 'temperature', 'voltage', 'timestamp')] == [
    'rad', 'rad/s', 'degC', 'V', 's']  # fmt: skip
  assert columns['observation.claw_qpos']['names'] == _CLAW_JOINTS
  assert description['domain'] is None  # The Recorder was not told.


def test_a_replay_is_not_split_over_workers(tmp_path):
  # Each worker would start from the recording's first episode.
  with pytest.raises(ValueError, match='not with a replay'):
    evaluation.evaluate(
      evaluation.EvalConfig(
        'dclaw', 'pose_fixed', 2, policy=f'replay:{tmp_path}', workers=2
      )
    )


def test_a_lock_file_that_cannot_be_opened_is_a_recording_error(tmp_path):
  from robel_dm.recording import format as format_lib  # noqa: PLC0415

  format_lib.prepare(tmp_path)
  (tmp_path / format_lib.LOCK).mkdir()  # Not a file: open() fails.
  with pytest.raises(recording.RecordingError, match='cannot lock'):
    format_lib.lock(tmp_path)


@pytest.mark.slow
def test_one_recorder_at_a_time_per_directory(tmp_path):
  # Two recorders would number their episodes alike and overwrite files.
  first = recording.Recorder(suite.load('dclaw', 'pose_fixed'), tmp_path)
  env = suite.load('dclaw', 'pose_fixed')
  with pytest.raises(recording.RecordingError, match='another process'):
    recording.Recorder(env, tmp_path)
  first.reset()
  first.close()
  second = recording.Recorder(env, tmp_path)  # Free once the first closed.
  second.close()


@pytest.mark.slow
def test_a_killed_recorder_leaves_the_directory_free(tmp_path):
  script = (
    'import os, signal\n'
    'from robel_dm import recording, suite\n'
    'env = suite.load("dclaw", "pose_fixed")\n'
    f'env = recording.Recorder(env, {str(tmp_path)!r})\n'
    'env.reset()\n'
    'os.kill(os.getpid(), signal.SIGKILL)\n'
  )
  done = subprocess.run([sys.executable, '-c', script], timeout=120)
  assert done.returncode == -9
  recording.Recorder(suite.load('dclaw', 'pose_fixed'), tmp_path).close()


@pytest.mark.slow
def test_recorders_starting_together_cannot_mix_tasks(tmp_path, monkeypatch):
  # B finds the directory empty; before B takes the lock, A (another task)
  # starts, records and closes. B must look again once it holds the lock.
  from robel_dm.recording import format as format_lib  # noqa: PLC0415

  prepare = format_lib.prepare

  def prepare_while_another_records(directory):
    monkeypatch.setattr(format_lib, 'prepare', prepare)
    _record_directly(directory, {'domain': 'dclaw', 'task': 'turn_random'})
    prepare(directory)

  monkeypatch.setattr(format_lib, 'prepare', prepare_while_another_records)
  env = suite.load('dclaw', 'pose_fixed')
  try:
    with pytest.raises(
      recording.RecordingError,
      match='holds a recording of dclaw/turn_random .*not dclaw/pose_fixed',
    ):
      recording.Recorder(
        env, tmp_path, metadata={'domain': 'dclaw', 'task': 'pose_fixed'}
      )
  finally:
    env.close()
  info = json.loads((tmp_path / 'meta/info.json').read_text())
  assert info['session']['task'] == 'turn_random'
  assert [e.metadata['task'] for e in recording.read(tmp_path)] == [
    'turn_random'
  ]
  # The refused recorder let the lock go.
  _record_directly(tmp_path, {'domain': 'dclaw', 'task': 'turn_random'})
