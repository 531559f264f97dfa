"""System identification: calibration files, the simulated delay, and the
fit recovering a virtual robot's known dynamics through the real SDK."""

import importlib.util
import json
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from robel_dm import calibration, recording, suite
from robel_dm.sysid import excite, fit
from robel_dm.tasks import excitation

# Tests that write or read recordings (Parquet, Arrow) need the data extra;
# the rest (calibrations, the delay, excitation) run without it.
needs_pyarrow = pytest.mark.skipif(
  importlib.util.find_spec('pyarrow') is None,
  reason='recordings need pyarrow (the data extra)',
)

CLAW_JOINTS = ('FFJ10', 'FFJ11', 'FFJ12', 'MFJ20', 'MFJ21', 'MFJ22',
               'THJ30', 'THJ31', 'THJ32')  # fmt: skip
# Model values of the D'Claw (xml/dclaw/dclaw.xml).
CLAW_NOMINAL = {'kp': 2.0, 'damping': 0.1, 'armature': 0.001}


def _truth(seed=1, delay=0.0075) -> calibration.Calibration:
  """A D'Claw unlike the model: every joint's kp, damping and armature
  scaled by its own factor in [0.6, 1.6], friction loss 0.02 N m (the
  model has none) and a 7.5 ms delay (the model has none)."""
  factors = np.random.default_rng(seed).uniform(0.6, 1.6, (9, 3))
  joints = {
    name: {
      'kp': CLAW_NOMINAL['kp'] * f[0],
      'damping': CLAW_NOMINAL['damping'] * f[1],
      'armature': CLAW_NOMINAL['armature'] * f[2],
      'frictionloss': 0.02,
    }
    for name, f in zip(CLAW_JOINTS, factors, strict=True)
  }
  return calibration.Calibration('dclaw', joints, control_delay=delay)


def _record_excitation(directory, duration, device_path=None, dynamics=None):
  env = suite.load_excitation(
    'dclaw',
    duration,
    seed=0,
    dynamics=dynamics,
    robot=device_path and suite.RobotOptions(device_path),
  )
  metadata = {'kind': 'excitation', 'domain': 'dclaw'}
  env = recording.Recorder(env, directory, metadata=metadata)
  try:
    return excite.run(env, excite.Excitation(duration=duration))
  finally:
    env.close()


@pytest.mark.slow
@needs_pyarrow
def test_fit_recovers_a_virtual_robots_dynamics(tmp_path):
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  truth = _truth()
  # The virtual bus's simulation runs the changed robot; the excitation
  # goes out and the state comes back through dynamixel_sdk. Five seconds
  # of it fit every parameter within 4% (the fit's time grows with it).
  _record_excitation(tmp_path, 5.0, device_path='virtual', dynamics=truth)
  (episode,) = recording.read(tmp_path)
  assert 'motor.current' in episode.steps
  assert episode.metadata['robot']['joints'][0]['id'] == 10

  result = fit.fit(fit.load_trajectories(tmp_path, 'dclaw'), 'dclaw')

  for name in ('kp', 'damping', 'armature', 'frictionloss'):
    true = np.array([truth.joints[j][name] for j in CLAW_JOINTS])
    error = np.abs(result.fitted[name] / true - 1)
    assert error.max() < 0.15, (name, error.round(3))
  assert result.control_delay == pytest.approx(truth.control_delay)
  # Every joint's trajectory error at least halves (in fact ~20x).
  assert np.all(result.rms_after <= result.rms_before / 2)
  assert result.not_identified == []
  # The calibration round-trips through its file and loads in simulation.
  path = tmp_path / 'calibration.json'
  calibration.save(result.calibration, path)
  loaded = calibration.load(path)
  assert loaded.joints == result.calibration.joints
  assert loaded.fit['rms_angle_error_after'] == result.rms_after.tolist()


@pytest.mark.slow
def test_a_calibration_sets_the_simulated_model(tmp_path):
  truth = _truth(delay=0.005)
  path = tmp_path / 'c.json'
  calibration.save(truth, path)
  env = suite.load('dclaw', 'pose_fixed', dynamics=str(path))
  physics = env.physics
  claw = env.task.robot
  joints, actuators = physics.bind(claw.joints), physics.bind(claw.actuators)
  for name in ('damping', 'armature', 'frictionloss'):
    expected = [truth.joints[j][name] for j in CLAW_JOINTS]
    np.testing.assert_allclose(getattr(joints, name), expected)
  kp = [truth.joints[j]['kp'] for j in CLAW_JOINTS]
  np.testing.assert_allclose(actuators.gainprm[:, 0], kp)
  np.testing.assert_allclose(actuators.biasprm[:, 1], -np.array(kp))
  assert env.control_delay == pytest.approx(0.005)
  env.close()


def test_the_delay_holds_the_previous_targets():
  delayed = suite.load('dclaw', 'pose_fixed', dynamics=_truth(delay=0.005))
  delayed.reset()
  physics = delayed.physics
  # Replay the same control step by hand on a copy of the state.
  model, data = physics.model.ptr, physics.data.ptr
  copy = mujoco.MjData(model)
  mujoco.mj_copyData(copy, model, data)
  action = np.full(9, 0.5)
  delayed.step(action)
  targets = physics.bind(delayed.task.robot.actuators).ctrl.copy()
  mujoco.mj_step(model, copy, 2)  # 5 ms with the reset's targets.
  copy.ctrl[:] = targets
  mujoco.mj_step(model, copy, 18)
  np.testing.assert_array_equal(copy.qpos, physics.data.qpos)
  np.testing.assert_array_equal(copy.qvel, physics.data.qvel)
  delayed.close()


@pytest.mark.slow
def test_no_delay_is_the_uncalibrated_simulation():
  plain = suite.load('dclaw', 'pose_random', seed=4)
  zero = calibration.Calibration('dclaw', {'FFJ10': {'kp': 2.0}})
  calibrated = suite.load('dclaw', 'pose_random', seed=4, dynamics=zero)
  plain.reset(), calibrated.reset()
  for _ in range(20):
    a = plain.step(np.full(9, 0.3)).observation
    b = calibrated.step(np.full(9, 0.3)).observation
    for key in a:
      np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.parametrize(
  'change, message',
  [
    ({'domain': 'dkitty'}, 'calibrates a dkitty, not a dclaw'),
    ({'joints': {'XXJ': {'kp': 1.0}}}, "joints ['XXJ'] are not dclaw joints"),
    ({'joints': {'FFJ10': {'kp': -1.0}}}, 'joints.FFJ10.kp must be finite'),
    ({'joints': {'FFJ10': {'kp': 0}}}, 'joints.FFJ10.kp must be finite'),
    ({'joints': {'FFJ10': {'damping': 'x'}}}, 'must be a number'),
    ({'joints': {'FFJ10': {'gain': 1.0}}}, "unknown parameters ['gain']"),
    ({'control_delay': float('nan')}, 'control_delay must be finite'),
    (
      {'control_delay': 0.1},
      'bad.json: control_delay 0.1 s is not below the control step of',
    ),
    ({'format': 'other'}, 'not a robel_dm calibration'),
    ({'version': 9}, 'calibration version 9'),
  ],
)
def test_bad_calibrations_are_named(tmp_path, change, message):
  data = {**_truth().to_dict(), **change}
  path = tmp_path / 'bad.json'
  path.write_text(json.dumps(data))
  with pytest.raises(ValueError, match=message.replace('[', r'\[')):
    suite.load('dclaw', 'pose_fixed', dynamics=str(path))


def test_missing_calibration_and_real_robots_are_refused(tmp_path):
  with pytest.raises(calibration.CalibrationError, match='no calibration'):
    suite.load('dclaw', 'pose_fixed', dynamics=str(tmp_path / 'none.json'))
  # Refused before any port is opened.
  with pytest.raises(ValueError, match='calibrates a simulated robot'):
    suite.load(
      'dclaw',
      'pose_fixed',
      robot=suite.RobotOptions('/dev/nonexistent'),
      dynamics=_truth(),
    )


def test_excitation_targets_stay_in_range_and_move_chosen_joints():
  task = excitation.JointExcitation('dclaw', 4.0)
  env = suite.load_excitation('dclaw', 4.0)
  env.reset()
  low, high = env.task.action_range(env.physics)
  for signal in excite.SIGNALS:
    sequence = excite.targets(
      excite.Excitation(signal=signal, duration=4.0, joints=('MFJ21',)),
      CLAW_JOINTS, task.center_pose, low, high, 0.02,
    )  # fmt: skip
    assert sequence.shape == (200, 9)
    assert np.all(sequence >= low) and np.all(sequence <= high)
    moving = np.ptp(sequence, axis=0) > 0
    assert moving.tolist() == [name == 'MFJ21' for name in CLAW_JOINTS]
  with pytest.raises(ValueError, match="unknown joints \\['XX'\\]"):
    excite.targets(
      excite.Excitation(joints=('XX',)), CLAW_JOINTS, task.center_pose,
      low, high, 0.02,
    )  # fmt: skip
  with pytest.raises(ValueError, match='signal must be one of'):
    excite.Excitation(signal='noise')
  with pytest.raises(ValueError, match='duration must be positive'):
    excite.Excitation(duration=float('inf'))
  # An amplitude the range cannot hold is refused, not clipped: around the
  # pose, MFJ21 has room for 0.503 of its half range, MFJ22 for 0.478.
  for joints, fits in (('MFJ21',), True), (('MFJ21', 'MFJ22'), False):
    arguments = (CLAW_JOINTS, task.center_pose, low, high, 0.02)
    chosen = excite.Excitation(amplitude=0.5, joints=joints)
    if fits:
      sequence = excite.targets(chosen, *arguments)
      assert np.all(sequence >= low + excite.RANGE_MARGIN)
      assert np.all(sequence <= high - excite.RANGE_MARGIN)
    else:
      with pytest.raises(
        ValueError, match='takes MFJ22 beyond .* at most 0.47'
      ):
        excite.targets(chosen, *arguments)
  env.close()


@pytest.mark.slow
@needs_pyarrow
def test_command_line_excites_and_fits_in_simulation(tmp_path):
  record, output = tmp_path / 'rec', tmp_path / 'cal.json'
  run = [sys.executable, '-m', 'robel_dm.commands.sysid']
  excited = subprocess.run(
    [*run, 'excite', '--domain=dkitty', '--duration=2', f'--record={record}'],
    capture_output=True, text=True, timeout=300,
  )  # fmt: skip
  assert excited.returncode == 0, excited.stderr
  assert 'recorded 1 episodes, 100 steps' in excited.stdout
  fitted = subprocess.run(
    [*run, 'fit', str(record), '--domain=dkitty', '--parameters=kp,damping',
     f'--output={output}'],
    capture_output=True, text=True, timeout=300,
  )  # fmt: skip
  assert fitted.returncode == 0, fitted.stderr
  assert 'RMS angle error' in fitted.stdout
  result = calibration.load(output)
  # The simulation fitted to itself: the model's own values.
  for values in result.joints.values():
    assert values['kp'] == pytest.approx(5.0, rel=0.02)
    assert values['damping'] == pytest.approx(1.0, rel=0.02)
  assert result.control_delay == 0.0
  # A directory of the other robot, or of no excitation, is named.
  wrong = subprocess.run(
    [*run, 'fit', str(record), '--domain=dclaw'],
    capture_output=True, text=True, timeout=300,
  )  # fmt: skip
  assert wrong.returncode == 2
  assert 'excites a dkitty, not a dclaw' in wrong.stderr


@pytest.mark.slow
@needs_pyarrow
def test_command_line_errors_are_one_line(tmp_path):
  run = [sys.executable, '-m', 'robel_dm.commands.sysid']
  cases = [
    (['excite', '--domain=dclaw'], 'excite needs --record=DIR'),
    (['excite', f'--record={tmp_path / "r"}', '--joints=FFJ10,XX'],
     "unknown joints ['XX']"),
    # Before the robot's port is opened (there is none here).
    (['excite', f'--record={tmp_path / "r"}', '--joints=XX',
      '--device_path=/dev/robel_dm_none'], "unknown joints ['XX']"),
    (['excite', f'--record={tmp_path / "r"}', '--dynamics=none.json'],
     'no calibration file none.json'),
    (['fit', str(tmp_path), '--domain=dclaw'], 'is not a robel_dm recording'),
    (['fit', '--domain=dclaw'], 'fit needs the recording directories'),
    (['excite', f'--record={tmp_path / "r"}', '--device_path='],
     '--device_path is empty'),
    # A flag of the other command is refused, not ignored.
    (['excite', f'--record={tmp_path / "r"}', '--output=cal.json'],
     '--output is a flag of fit, not of excite'),
    (['fit', str(tmp_path), '--dynamics=cal.json'],
     '--dynamics is a flag of excite, not of fit'),
    # Where the calibration goes is checked before the fit.
    (['fit', str(tmp_path), f'--output={tmp_path / "no" / "cal.json"}'],
     f'--output: no folder {tmp_path / "no"}'),
  ]  # fmt: skip
  for arguments, message in cases:
    done = subprocess.run(
      [*run, *arguments], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2, (arguments, done.stderr)
    assert message in done.stderr, (arguments, done.stderr)
    assert 'Traceback' not in done.stderr
