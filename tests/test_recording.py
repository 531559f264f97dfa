"""Recordings: every timestep on disk as it happens, read back, replayed."""

import json
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip('pyarrow', reason='needs robel_dm[data]')

from robel_dm import evaluation, policies, recording, suite  # noqa: E402


@pytest.mark.slow
def test_every_field_round_trips_in_simulation(tmp_path):
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dkitty', 'stand_fixed', 2, policy='zero', seed=3, record=str(tmp_path)
    )
  )
  episodes = recording.read(tmp_path)
  assert [e.metadata['complete'] for e in episodes] == [True, True]
  assert [e.metadata['seed'] for e in episodes] == [3, 3]
  for episode, record in zip(episodes, results['records'], strict=True):
    steps = episode.steps
    assert len(episode) == record['steps'] + 1  # The reset's row too.
    assert np.isnan(steps['next.reward'][0])
    assert np.nansum(steps['next.reward']) == pytest.approx(record['return'])
    assert bool(steps['observation.success'][-1]) == record['success']
    assert steps['observation.kitty_qpos'].shape == (len(episode), 12)
    assert steps['action'].shape == (len(episode), 12)
    assert steps['joint_targets'].shape == (len(episode), 12)
    assert list(steps['frame_index']) == list(range(len(episode)))
    assert steps['next.done'][-1] and not steps['next.done'][:-1].any()
    terms = [k for k in steps if k.startswith('reward_terms.')]
    total = sum(steps[k][1:] for k in terms)
    np.testing.assert_allclose(total, steps['next.reward'][1:])
  info = json.loads((tmp_path / 'meta/info.json').read_text())
  assert info['format'] == 'robel_dm-recording' and info['fps'] == 10


def test_parquet_files_open_with_pyarrow_alone(tmp_path):
  import pyarrow.parquet as pq  # noqa: PLC0415

  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 1, policy='zero', record=tmp_path
    )
  )
  (path,) = (tmp_path / 'data/chunk-000').glob('*.parquet')
  table = pq.read_table(path)
  assert {'episode_index', 'frame_index', 'timestamp', 'action',
          'next.reward', 'next.done', 'observation.qpos'} <= set(
    table.column_names
  )  # fmt: skip


@pytest.mark.slow
def test_motor_state_is_recorded_on_the_virtual_bus(tmp_path):
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  evaluation.evaluate(evaluation.EvalConfig(
    'dclaw', 'pose_fixed', 1, policy='zero',
    robot=suite.RobotOptions('virtual'), record=str(tmp_path),
  ))  # fmt: skip
  (episode,) = recording.read(tmp_path)
  for column in ('motor.position', 'motor.velocity', 'motor.current'):
    assert episode.steps[column].shape == (len(episode), 9)
    assert np.isfinite(episode.steps[column]).all()
  np.testing.assert_allclose(
    episode.steps['motor.position'], episode.steps['observation.qpos']
  )
  assert episode.metadata['device_path'] == 'virtual'


@pytest.mark.slow
def test_replay_reproduces_a_simulated_episode_exactly(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'turn_random', 2, policy='random', seed=5, record=tmp_path / 'a'
    )
  )
  evaluation.evaluate(evaluation.EvalConfig(
    'dclaw', 'turn_random', 2, policy=f'replay:{tmp_path / "a"}', seed=5,
    record=tmp_path / 'b',
  ))  # fmt: skip
  for first, again in zip(
    recording.read(tmp_path / 'a'), recording.read(tmp_path / 'b'), strict=True
  ):
    for key in ('observation.claw_qpos', 'observation.target_error',
                'next.reward'):  # fmt: skip
      np.testing.assert_array_equal(first.steps[key], again.steps[key])
  with pytest.raises(policies.PolicyError, match='recording .* is of'):
    evaluation.evaluate(
      evaluation.EvalConfig(
        'dclaw', 'pose_fixed', 1, policy=f'replay:{tmp_path / "a"}'
      )
    )


@pytest.mark.slow
def test_demonstrations_from_the_reference_controller_load(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_random', 3, policy='reference', record=str(tmp_path)
    )
  )
  episodes = recording.read(tmp_path)
  assert len(episodes) == 3 and all(e.metadata['complete'] for e in episodes)
  assert all(e.metadata['policy'] == 'reference' for e in episodes)


def test_an_unwritable_directory_fails_before_the_first_step(tmp_path):
  blocker = tmp_path / 'file'
  blocker.write_text('not a directory')
  with pytest.raises(recording.RecordingError, match='cannot write'):
    evaluation.evaluate(
      evaluation.EvalConfig(
        'dclaw', 'pose_fixed', 1, record=str(blocker / 'rec')
      )
    )


def test_a_full_disk_fails_before_the_first_step(tmp_path, monkeypatch):
  import collections  # noqa: PLC0415
  import shutil  # noqa: PLC0415

  usage = collections.namedtuple('usage', 'total used free')
  monkeypatch.setattr(shutil, 'disk_usage', lambda path: usage(1, 1, 1000))
  with pytest.raises(recording.RecordingError, match='MiB free'):
    evaluation.evaluate(
      evaluation.EvalConfig('dclaw', 'pose_fixed', 1, record=str(tmp_path))
    )


@pytest.mark.slow
def test_kill_9_keeps_every_step_older_than_a_second(tmp_path):
  code = f"""
import time, numpy as np
from robel_dm import suite, recording
env = recording.Recorder(suite.load('dclaw', 'pose_fixed', seed=0),
                         {str(tmp_path)!r}, metadata={{'task': 'pose_fixed'}})
timestep = env.reset()
while not timestep.last():  # One full episode first.
  timestep = env.step(np.zeros(9))
env.close()
# Then an episode without end, cut by the kill.
env = recording.Recorder(
  suite.load('dclaw', 'pose_fixed', seed=0, time_limit=float('inf')),
  {str(tmp_path)!r}, metadata={{'task': 'pose_fixed'}})
env.reset()
steps = 0
while True:
  env.step(np.zeros(9))
  steps += 1
  print(steps, time.monotonic(), flush=True)
  time.sleep(0.02)
"""
  process = subprocess.Popen(
    [sys.executable, '-c', code], stdout=subprocess.PIPE, text=True
  )
  lines = []
  start = time.monotonic()
  while time.monotonic() - start < 30:
    lines.append(process.stdout.readline().split())
    if len(lines) > 1 and float(lines[-1][1]) - float(lines[0][1]) > 2.5:
      break
  killed_at = time.monotonic()
  process.send_signal(signal.SIGKILL)
  process.wait(10)
  # Steps the child completed more than a second before the kill.
  old = [int(n) for n, t in lines if killed_at - float(t) > 1.0]
  episodes = recording.read(tmp_path)
  assert episodes[0].metadata['complete'] and len(episodes[0]) == 81
  partial = episodes[1]
  assert partial.metadata['complete'] is False
  assert len(partial) - 1 >= max(old)  # Minus the reset's row.


@pytest.mark.slow
def test_the_command_line_summarizes_a_recording(tmp_path):
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 2, policy='zero', record=tmp_path
    )
  )
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.recording', str(tmp_path)],
    capture_output=True, text=True, check=False,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  # Control steps, not rows: the reset's row of each episode is not one.
  assert '2 episodes, 160 steps' in result.stdout
  assert [line.split()[1] for line in result.stdout.splitlines()[1:3]] == [
    '80',
    '80',
  ]
  bad = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.recording',
     str(pathlib.Path('/nope'))],
    capture_output=True, text=True, check=False,
  )  # fmt: skip
  assert bad.returncode == 2 and 'not a robel_dm recording' in bad.stderr


@pytest.mark.slow
def test_motor_health_and_faults_are_recorded_on_the_virtual_bus(tmp_path):
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  from robel_dm import suite  # noqa: PLC0415
  from robel_dm.hardware.dynamixel import control_table as table  # noqa: PLC0415

  env = recording.Recorder(
    suite.load('dclaw', 'pose_fixed', robot=suite.RobotOptions('virtual')),
    tmp_path,
  )
  servos = {servo.motor_id: servo for servo in env.virtual_bus.servos}
  servos[21].set(table.PRESENT_TEMPERATURE, 52)
  env.reset()
  for _ in range(12):  # Health is read at the reset and every 10 steps.
    env.step(np.zeros(9))
  servos[31].inject_hardware_error(0b100)  # Overheating (bit 2).
  with pytest.raises(Exception, match='hardware error'):
    for _ in range(10):
      env.step(np.zeros(9))
  env.close()
  (episode,) = recording.read(tmp_path)
  steps = episode.steps
  ids = [m['id'] for m in episode.metadata['robot']['joints']]
  assert ids == [10, 11, 12, 20, 21, 22, 30, 31, 32]
  temperatures = steps['motor.temperature'][:, :9]
  assert temperatures[:, ids.index(21)].tolist() == [52] * len(episode)
  assert set(temperatures[:, ids.index(10)]) == {35}
  volts = servos[10].get(table.PRESENT_INPUT_VOLTAGE) * table.VOLTS_PER_UNIT
  assert volts > 0 and np.all(steps['motor.voltage'] == volts)
  assert not steps['motor.hardware_error'].any()
  health_times = steps['motor.health_timestamp']
  assert np.isfinite(health_times).all() and len(set(health_times)) == 2
  # The fault ended the episode, and its metadata says why.
  assert episode.metadata['complete'] is False
  assert 'hardware error' in episode.metadata['error']
  assert '31' in episode.metadata['error']  # The motor is named.


class _FaultingEnv:
  """A simulated D'Claw whose steps fail as a motor fault or Ctrl-C would,
  and whose close() (a robot's release) is logged."""

  def __init__(self, events):
    self._env = suite.load('dclaw', 'pose_fixed')
    self._events = events

  def __getattr__(self, name):
    return getattr(self._env, name)

  def step(self, action):
    raise KeyboardInterrupt

  def close(self):
    self._events.append('released')
    self._env.close()


@pytest.mark.parametrize('finishing_fails', [False, True])
def test_a_fault_releases_the_robot_before_its_episode_is_written(
  tmp_path, monkeypatch, finishing_fails
):
  from robel_dm.recording import format as format_lib  # noqa: PLC0415

  events, finish = [], format_lib.EpisodeWriter.finish

  def logged_finish(writer, metadata):
    events.append('written')
    if finishing_fails:
      raise recording.RecordingError('the disk is full')
    finish(writer, metadata)

  monkeypatch.setattr(format_lib.EpisodeWriter, 'finish', logged_finish)
  env = recording.Recorder(_FaultingEnv(events), tmp_path)
  env.reset()
  # The caller's `finally` closes; the fault, not the recording, propagates.
  with pytest.raises(KeyboardInterrupt):
    try:
      env.step(np.zeros(9))
    finally:
      assert events == []  # Nothing written while the robot is held.
      env.close()
  assert events == ['released', 'written']
  if not finishing_fails:
    (episode,) = recording.read(tmp_path)
    assert episode.metadata['complete'] is False
    assert episode.metadata['error'] == 'KeyboardInterrupt: '
