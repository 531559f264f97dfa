"""The tracker layer: frames, calibration, velocities, targets, and the
D'Kitty's torso tracked on the virtual bus (NatNet itself is in
test_tracking_natnet.py)."""

import math

import mujoco
import numpy as np
import pytest

from robel_dm import geometry as geo
from robel_dm import suite
from robel_dm.hardware.tracking import tracker as tr


def _rotation(axis, angle):
  return geo.quat_from_rotation_vector(np.asarray(axis, float) * angle)


def _quat_error(a, b) -> float:
  """Distance between quaternions up to sign (q and -q: the same rotation)."""
  a, b = np.asarray(a), np.asarray(b)
  return float(min(np.abs(a - b).max(), np.abs(a + b).max()))


class _Clock:
  """A settable clock for `TorsoTracker` and the simulated sources."""

  def __init__(self, now=0.0):
    self.now = now

  def __call__(self):
    return self.now


def _moving_source(
  clock,
  position,
  quaternion,
  velocity=(0, 0, 0),
  angular_velocity_body=(0, 0, 0),
  body='torso',
):
  """A body at constant linear velocity (tracker frame) and constant
  body-frame angular velocity: p(t) = p + v t, q(t) = q exp(w t / 2)."""
  position, velocity = np.asarray(position, float), np.asarray(velocity, float)
  omega = np.asarray(angular_velocity_body, float)

  def poses():
    t = clock.now
    q = geo.quat_multiply(quaternion, geo.quat_from_rotation_vector(omega * t))
    return {body: tr.Pose(position + velocity * t, q, t)}

  return tr.SimulatedSource(poses)


# --- Quaternion helpers -------------------------------------------------------


def test_quaternion_helpers():
  rng = np.random.default_rng(0)
  for _ in range(20):
    q = geo.quat_normalize(rng.normal(size=4))
    assert _quat_error(geo.matrix_to_quat(geo.quat_to_matrix(q)), q) < 1e-12
    vector = rng.uniform(-1, 1, 3)
    assert np.allclose(
      geo.quat_to_rotation_vector(geo.quat_from_rotation_vector(vector)), vector
    )
  assert np.allclose(
    geo.matrix_to_quat(tr.Y_UP_TO_Z_UP) @ [1, 0, 0, 0], 0.5**0.5
  )
  with pytest.raises(ValueError, match='proper rotation'):
    geo.matrix_to_quat(np.diag([1.0, 1.0, -1.0]))
  # Markley's mean ignores each sample's sign; a component mean would not.
  mean = _rotation([0, 0, 1], 0.3)
  samples = [
    sign * geo.quat_multiply(mean, _rotation(rng.normal(size=3), 0.01))
    for sign in (1, -1, 1, -1, -1, 1)
  ]
  assert _quat_error(geo.average_quaternions(samples), mean) < 0.01


# --- Frames, calibration, velocities ------------------------------------------


def test_y_up_tracker_frame_is_converted_to_z_up():
  clock = _Clock()
  level_in_y_up = geo.matrix_to_quat(tr.Y_UP_TO_Z_UP.T)
  source = _moving_source(
    clock, (0.5, 0.2, -0.1), level_in_y_up, velocity=(0.0, 0.3, 0.0)
  )
  tracker = tr.TorsoTracker(
    source, 'torso', frames=tr.Frames(tr.Y_UP_TO_Z_UP), clock=clock
  )
  start, quaternion, _, _ = tracker.torso_state()
  # Tracker (x, y, z) -> world (x, -z, y).
  assert np.allclose(start, (0.5, 0.1, 0.2))
  assert geo.quat_to_matrix(quaternion)[2, 2] == pytest.approx(1.0)  # Upright.
  clock.now = 0.1
  end, _, velocity, _ = tracker.torso_state()
  # Moving up in the tracker (its +y) is moving up in robel_dm (+z).
  assert np.allclose(end - start, (0.0, 0.0, 0.03))
  assert np.allclose(velocity, (0.0, 0.0, 0.3))
  # Without the conversion (ROBEL 0.1.2's bug) the same torso would read as
  # lying on its side and moving sideways.
  clock.now = 0.0
  raw = tr.TorsoTracker(source, 'torso', clock=clock)
  _, quaternion, _, _ = raw.torso_state()
  assert abs(geo.quat_to_matrix(quaternion)[2, 2]) < 1e-9


def test_origin_calibration_levels_position_and_heading_keeps_tilt():
  clock = _Clock()
  rng = np.random.default_rng(1)
  # A torso rolled and pitched a little, turned by 2 rad, away from the
  # tracker's origin; in a y-up tracker frame, with jitter.
  tilt = geo.quat_multiply(
    _rotation([1, 0, 0], 0.2), _rotation([0, 1, 0], -0.1)
  )
  torso = geo.quat_multiply(_rotation([0, 0, 1], 2.0), tilt)
  to_tracker = geo.matrix_to_quat(tr.Y_UP_TO_Z_UP.T)
  tracker_q = geo.quat_multiply(to_tracker, torso)
  tracker_p = tr.Y_UP_TO_Z_UP.T @ np.array([1.2, -0.7, 0.25])
  samples = []

  def poses():
    clock.now += 0.01
    jitter = rng.normal(scale=0.001, size=3)
    sign = rng.choice([-1.0, 1.0])  # Either hemisphere.
    q = sign * geo.quat_multiply(
      tracker_q, _rotation(rng.normal(size=3), 0.002)
    )
    samples.append(tracker_p + jitter)
    return {'torso': tr.Pose(tracker_p + jitter, q, clock.now)}

  tracker = tr.TorsoTracker(
    tr.SimulatedSource(poses),
    'torso',
    frames=tr.Frames(tr.Y_UP_TO_Z_UP),
    clock=clock,
  )
  calibration = tracker.calibrate_origin(samples=10)
  assert calibration.samples == 10 and len(samples) == 10
  assert calibration.yaw == pytest.approx(2.0, abs=0.01)
  assert calibration.spread < 0.01
  position, quaternion, _, _ = tracker.torso_state()
  # Within the jitter of the last sample.
  assert np.allclose(position, tr.ORIGIN, atol=0.005)
  matrix = geo.quat_to_matrix(quaternion)
  assert geo.heading(quaternion) == pytest.approx(0.0, abs=0.01)
  assert matrix[0, 1] == pytest.approx(0.0, abs=0.01) and matrix[1, 1] > 0
  # Tilt kept: the torso axes' vertical components are unchanged.
  assert np.allclose(matrix[2], geo.quat_to_matrix(torso)[2], atol=0.01)
  assert tr.ORIGIN[2] == 0.3


def test_moving_forward_after_calibration_is_moving_along_y():
  clock = _Clock()
  heading = _rotation([0, 0, 1], -2.5)
  forward = geo.quat_to_matrix(heading) @ [0, 1, 0]  # Level frame.
  tracked = geo.quat_multiply(geo.matrix_to_quat(tr.Y_UP_TO_Z_UP.T), heading)
  velocity = tr.Y_UP_TO_Z_UP.T @ (0.2 * forward)  # Tracker frame.
  source = _moving_source(clock, (3.0, 0.3, 1.0), tracked, velocity=velocity)
  tracker = tr.TorsoTracker(
    source, 'torso', frames=tr.Frames(tr.Y_UP_TO_Z_UP), clock=clock
  )
  tracker.calibrate_origin(samples=3)
  clock.now = 0.5
  tracker.torso_state()
  clock.now = 1.0
  position, _, world_velocity, _ = tracker.torso_state()
  assert np.allclose(position, tr.ORIGIN + (0.0, 0.2, 0.0))
  assert np.allclose(world_velocity, (0.0, 0.2, 0.0))


def test_finite_difference_velocities_with_mounting_and_calibration():
  clock = _Clock()
  omega_torso = np.array([0.3, -1.2, 2.0])  # rad/s, torso frame.
  velocity_level = np.array([0.4, -0.1, 0.05])  # m/s, z-up tracker frame.
  # The tracked body is mounted rotated and offset on the torso.
  mount = _rotation([1, 1, 0] / np.sqrt(2), 0.7)  # Torso in body frame.
  offset = np.array([0.02, -0.05, 0.1])  # Torso origin in body frame.
  torso0 = geo.quat_multiply(
    _rotation([0, 0, 1], 0.9), _rotation([1, 0, 0], 0.1)
  )
  start = np.array([0.3, 0.2, 0.25])

  def poses():
    t = clock.now
    torso = geo.quat_multiply(
      torso0, geo.quat_from_rotation_vector(omega_torso * t)
    )
    body = geo.quat_multiply(torso, geo.quat_conjugate(mount))
    body_p = start + velocity_level * t - geo.quat_to_matrix(body) @ offset
    body_q = geo.quat_multiply(geo.matrix_to_quat(tr.Y_UP_TO_Z_UP.T), body)
    return {'7': tr.Pose(tr.Y_UP_TO_Z_UP.T @ body_p, body_q, t)}

  tracker = tr.TorsoTracker(
    tr.SimulatedSource(poses),
    7,
    frames=tr.Frames(tr.Y_UP_TO_Z_UP, geo.quat_to_matrix(mount), offset),
    clock=clock,
  )
  calibration = tracker.calibrate_origin(samples=1)
  yaw = geo.quat_to_matrix(geo.yaw_quaternion(-calibration.yaw))
  for step in range(1, 30):  # A 100 Hz tracker.
    clock.now = 0.01 * step
    position, quaternion, velocity, angular_velocity = tracker.torso_state()
    assert np.allclose(velocity, yaw @ velocity_level, atol=1e-9)
    assert np.allclose(angular_velocity, omega_torso, atol=1e-9)
  assert np.allclose(
    position, tr.ORIGIN + yaw @ (velocity_level * clock.now), atol=1e-9
  )
  # The same measurement twice (dt = 0) keeps the estimate; time running
  # backwards (a restarted source) restarts it from zero.
  assert np.allclose(tracker.torso_state()[3], omega_torso)
  clock.now -= 0.5
  assert np.allclose(tracker.torso_state()[3], 0.0)


def test_velocity_low_pass():
  clock = _Clock()
  source = _moving_source(clock, (0, 0, 0), (1, 0, 0, 0), velocity=(1, 0, 0))
  tracker = tr.TorsoTracker(
    source, 'torso', velocity_time_constant=0.05, clock=clock
  )
  tracker.torso_state()
  speeds = []
  for step in range(1, 41):
    clock.now = 0.01 * step
    speeds.append(tracker.torso_state()[2][0])
  assert speeds[0] == pytest.approx(0.01 / 0.06)  # One step of dt/(tau+dt).
  assert np.all(np.diff(speeds) > 0) and speeds[-1] > 0.99


def test_missing_or_stale_tracker_raises_clear_errors():
  clock = _Clock()
  visible = {'on': False}

  def poses():
    pose = tr.Pose((0, 0, 0.3), (1, 0, 0, 0), clock.now)
    return {'kitty': pose} if visible['on'] else {}

  tracker = tr.TorsoTracker(tr.SimulatedSource(poses), 'kitty', clock=clock)
  with pytest.raises(tr.TrackingError, match="no pose.*torso body 'kitty'"):
    tracker.torso_state()
  with pytest.raises(tr.TrackingError, match="0 of 3 poses.*'kitty'"):
    tracker.calibrate_origin(samples=3, timeout=0.05)
  visible['on'] = True
  assert len(tracker.torso_state()) == 4
  visible['on'] = False
  clock.now = 0.4
  tracker.torso_state()  # Not stale yet.
  clock.now = 0.6
  with pytest.raises(tr.TrackingError, match=r"'kitty'.*0.60 s ago"):
    tracker.torso_state()
  with pytest.raises(ValueError, match='no target body'):
    tracker.target_position()
  with pytest.raises(ValueError, match='stale_timeout'):
    tr.TorsoTracker(tr.SimulatedSource(poses), 'kitty', stale_timeout=0)
  with pytest.raises(ValueError, match='3x3 matrix or a quaternion'):
    tr.Frames(body_rotation=np.eye(2))
  closed = []
  source = tr.SimulatedSource(poses, on_close=lambda: closed.append(1))
  with tr.TorsoTracker(source, 'kitty'):
    pass
  assert closed == [1]
  with pytest.raises(tr.TrackingError, match='closed'):
    source.poll()


def test_targets_follow_the_calibrated_world():
  clock = _Clock()
  to_tracker = tr.Y_UP_TO_Z_UP.T
  turned = geo.quat_multiply(
    geo.matrix_to_quat(to_tracker), geo.yaw_quaternion(math.pi / 2)
  )
  # Level frame: torso at (1, 1, 0.3) facing -x; target 2 m ahead of it.
  level = {
    'torso': (1.0, 1.0, 0.3),
    'goal': (-1.0, 1.0, 0.0),
    'flag': (1.0, 3.0, 0.0),
  }

  def poses():
    return {
      name: tr.Pose(to_tracker @ p, turned, clock.now)
      for name, p in level.items()
    }

  source = tr.SimulatedSource(poses)
  tracker = tr.TorsoTracker(source, 'torso', 'ball', clock=clock)
  with pytest.raises(tr.TrackingError, match="target body 'ball'"):
    tracker.target_position()
  tracker = tr.TorsoTracker(
    source, 'torso', 'goal', frames=tr.Frames(tr.Y_UP_TO_Z_UP), clock=clock
  )
  tracker.calibrate_origin(samples=2)
  assert np.allclose(tracker.target_position(), (0.0, 2.0))
  assert np.allclose(tracker.heading_position(), (0.0, 2.0))  # Default.
  tracker = tr.TorsoTracker(
    source,
    'torso',
    'goal',
    'flag',
    frames=tr.Frames(tr.Y_UP_TO_Z_UP),
    clock=clock,
  )
  tracker.calibrate_origin(samples=2)
  assert np.allclose(tracker.heading_position(), (2.0, 0.0))


# --- The D'Kitty on the virtual bus -------------------------------------------

# At the control rate (10 Hz) the finite difference is the mean velocity over
# the 0.1 s step, off from the velocity at its end by up to |a| dt / 2. The
# standing D'Kitty under +-0.1 actions accelerates below ~0.5 m/s^2 and
# ~3 rad/s^2, so 0.025 m/s and 0.15 rad/s (measured: 0.011 and 0.068).
_CONTROL_RATE_VELOCITY_TOLERANCE = 0.025  # m/s
_CONTROL_RATE_ANGULAR_TOLERANCE = 0.15  # rad/s


def _tracked_virtual_kitty(emit=None):
  """The stand task on the virtual bus and a tracker of its simulated torso.

  Args:
    emit: maps the simulated torso (position, quaternion) to what the
      tracker source reports; identity if None.
  """
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  env = suite.load(
    'dkitty', 'stand_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  simulation = env.virtual_bus.driver

  def now():
    return float(simulation.physics.data.time)

  def poses():
    position, quaternion, _, _ = simulation.torso_pose()
    if emit is not None:
      position, quaternion = emit(position, quaternion)
    return {'torso': tr.Pose(position, quaternion, now())}

  return env, simulation, tr.SimulatedSource(poses), now


def _small_actions(env, steps):
  rng = np.random.default_rng(0)
  joints = env.physics.bind(env.task.robot.joints).qpos
  centre = env.task.normalize_joint_targets(joints)
  return np.clip(centre + rng.uniform(-0.1, 0.1, (steps, 12)), -1, 1)


@pytest.mark.slow
def test_tracker_reproduces_the_virtual_kittys_torso():
  env, simulation, source, now = _tracked_virtual_kitty()
  tracker = tr.TorsoTracker(source, 'torso', clock=now)
  try:
    env.reset()
    state = tracker.torso_state()
    # The free joint's contract: qpos (3 + 4) and qvel (3 + 3), floats.
    assert [np.shape(x) for x in state] == [(3,), (4,), (3,), (3,)]
    assert all(np.asarray(x).dtype == np.float64 for x in state)
    assert np.linalg.norm(state[1]) == pytest.approx(1.0)
    for action in _small_actions(env, 20):
      env.step(action)
      position, quaternion, velocity, angular_velocity = tracker.torso_state()
      truth = simulation.torso_pose()
      assert np.abs(position - truth[0]).max() < 1e-3
      assert _quat_error(quaternion, truth[1]) < 1e-3
      assert np.abs(velocity - truth[2]).max() < (
        _CONTROL_RATE_VELOCITY_TOLERANCE
      )
      assert np.abs(angular_velocity - truth[3]).max() < (
        _CONTROL_RATE_ANGULAR_TOLERANCE
      )
    # At the physics rate (a 400 Hz tracker), with the torso kicked into a
    # tumble, the estimates are exact: MuJoCo's semi-implicit Euler step
    # advances qpos with the new qvel (the free joint's quaternion by its
    # torso-frame angular velocity), exactly what the finite difference
    # inverts.
    model, data = simulation.physics.model, simulation.physics.data
    free = int(np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
    dof = int(model.jnt_dofadr[free])
    data.qvel[dof : dof + 6] = (0.3, -0.2, 1.0, 2.0, -1.5, 1.0)
    tracker.torso_state()
    speeds = []
    for _ in range(40):
      simulation.advance(model.opt.timestep)
      _, _, velocity, angular_velocity = tracker.torso_state()
      truth = simulation.torso_pose()
      assert np.allclose(velocity, truth[2], atol=1e-6)
      assert np.allclose(angular_velocity, truth[3], atol=1e-6)
      speeds.append(np.linalg.norm(truth[3]))
    assert max(speeds) > 0.3  # Really moving.
  finally:
    tracker.close()
    env.close()


@pytest.mark.slow
def test_tracker_recovers_the_torso_through_a_y_up_frame_and_a_mount():
  # The torso as a y-up tracker sees it: the world turned by 1 rad and
  # shifted, the tracked body mounted rotated and offset on the torso.
  world_turn = geo.yaw_quaternion(1.0)
  shift = np.array([2.0, -1.0, 0.1])
  mount = _rotation([0, 1, 0], math.pi / 2)  # Torso in the body's frame.
  offset = np.array([0.0, 0.03, 0.05])  # Torso origin in the body's frame.
  to_tracker = geo.matrix_to_quat(tr.Y_UP_TO_Z_UP.T)

  def emit(position, quaternion):
    torso = geo.quat_multiply(world_turn, quaternion)
    body = geo.quat_multiply(torso, geo.quat_conjugate(mount))
    body_p = geo.quat_to_matrix(world_turn) @ position + shift
    body_p = body_p - geo.quat_to_matrix(body) @ offset
    return tr.Y_UP_TO_Z_UP.T @ body_p, geo.quat_multiply(to_tracker, body)

  env, simulation, source, now = _tracked_virtual_kitty(emit)
  tracker = tr.TorsoTracker(
    source,
    'torso',
    frames=tr.Frames(tr.Y_UP_TO_Z_UP, mount, offset),
    clock=now,
  )
  try:
    env.reset()
    tracker.calibrate_origin()
    start, start_q, _, _ = simulation.torso_pose()
    # Calibration makes the reset pose the origin, facing +y: in the
    # simulation's world that is a turn by -heading and a shift.
    undo = geo.yaw_quaternion(-geo.heading(start_q))
    for action in _small_actions(env, 10):
      env.step(action)
      position, quaternion, velocity, angular_velocity = tracker.torso_state()
      truth = simulation.torso_pose()
      expected = tr.ORIGIN + geo.quat_to_matrix(undo) @ (truth[0] - start)
      assert np.abs(position - expected).max() < 1e-3
      assert _quat_error(quaternion, geo.quat_multiply(undo, truth[1])) < 1e-3
      # Uprightness is frame-independent.
      assert geo.quat_to_matrix(quaternion)[2, 2] == pytest.approx(
        geo.quat_to_matrix(truth[1])[2, 2], abs=1e-6
      )
      assert np.abs(velocity - geo.quat_to_matrix(undo) @ truth[2]).max() < (
        _CONTROL_RATE_VELOCITY_TOLERANCE
      )
      assert np.abs(angular_velocity - truth[3]).max() < (
        _CONTROL_RATE_ANGULAR_TOLERANCE
      )
  finally:
    tracker.close()
    env.close()
