"""The zoo of held-out robots and the transfer table (robel_dm.zoo)."""

import numpy as np
import pytest

from robel_dm import calibration, randomization, suite, zoo

# The robots run on the virtual bus.
pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')

_RANDOM_DYNAMICS = {
  'dclaw': randomization.DCLAW_POSE,
  'dkitty': randomization.DKITTY_STAND,
}


def _outside_random_dynamics(robot: zoo.ZooRobot) -> bool:
  """Whether the robot has something RandomDynamics never draws."""
  ranges = _RANDOM_DYNAMICS[robot.domain]
  values = calibration.load(robot.path)
  kps = {joint.get('kp') for joint in values.joints.values()}
  for joint in values.joints.values():
    for name, window in (('kp', ranges.actuator_kp),
                         ('damping', ranges.damping),
                         ('frictionloss', ranges.friction_loss)):  # fmt: skip
      if name in joint and not window.contains(joint[name]):
        return True
  uneven = len(kps) > 1  # RandomDynamics draws one gain for all servos.
  limited = any('max_torque' in joint for joint in values.joints.values())
  return uneven or limited or values.sensor_noise > 0


@pytest.mark.parametrize('domain', ['dclaw', 'dkitty'])
def test_the_zoo_has_five_documented_robots_per_domain(domain):
  robots = zoo.robots(domain)
  assert len(robots) == 5
  for robot in robots:
    values = calibration.load(robot.path)
    assert values.domain == domain
    assert len(robot.about) > 40, robot.name
  # Each partly outside what RandomDynamics trains on.
  outside = [r.name for r in robots if _outside_random_dynamics(r)]
  assert outside == [r.name for r in robots]


def test_an_unknown_robot_is_named_with_the_zoo():
  with pytest.raises(ValueError, match="no zoo robot 'claw_x'.*claw_worn"):
    zoo.robot('claw_x')


def test_a_weak_motor_is_torque_limited_and_the_others_are_not():
  env = suite.load(
    'dclaw', 'pose_fixed', dynamics=zoo.robot('claw_weak_finger').path
  )
  actuators = env.physics.bind(env.task.robot.actuators)
  assert list(actuators.forcelimited[:3]) == [1, 1, 1]
  assert actuators.forcerange[0].tolist() == [-0.5, 0.5]
  assert not any(actuators.forcelimited[3:])
  env.close()


def _sensing_error(robot_name: str) -> np.ndarray:
  """Reported minus true joint angles over a few steps, on a zoo robot."""
  env = suite.load(
    'dclaw',
    'pose_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual'),
    dynamics=zoo.robot(robot_name).path,
  )
  try:
    errors = []
    timestep = env.reset()
    for _ in range(5):
      true = env.simulated_robot.physics.bind(env.task.robot.joints).qpos
      errors.append(timestep.observation['qpos'] - true)
      timestep = env.step(np.zeros(env.action_spec().shape))
    return np.concatenate(errors)
  finally:
    env.close()


@pytest.mark.slow
def test_a_noisy_robot_reports_noisy_positions():
  half_tick = np.pi / 4096  # What rounding to ticks alone can add.
  assert np.abs(_sensing_error('claw_stiff')).max() <= half_tick + 1e-9
  noisy = _sensing_error('claw_noisy')
  assert 0.0035 < noisy.std() < 0.0065  # The file's 0.005 rad.
