"""Hardware resets on the virtual bus (robel_dm.hardware.resets)."""

import dataclasses

import numpy as np
import pytest

from robel_dm import robots, suite
from robel_dm.hardware import clock as clock_lib
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import resets
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.tracking import tracker as tracking

# Every test here runs on the virtual bus: skipped without the hardware
from robel_dm.hardware.virtual import sim_robot

# extra.
pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')


def _with_limits(domain, task, limits, **robot):
  """The task on the virtual bus, its configuration narrowed by `limits`."""
  config = dataclasses.replace(config_lib.default(domain), limits=limits)
  return suite.load(
    domain,
    task,
    seed=0,
    robot=suite.RobotOptions('virtual', robot_config=config, **robot),
  )


def _torque(bus):
  return {servo.motor_id: servo.torque_enabled for servo in bus.servos}


@pytest.mark.slow
def test_scripted_claw_reset_turns_the_valve_and_releases_it():
  env = suite.load(
    'dclaw', 'turn_random', seed=3, robot=suite.RobotOptions('virtual')
  )
  try:
    for _ in range(3):
      env.reset()
      valve = env.task.valve.hinge
      # The task drew an initial valve angle; the valve motor drove the
      # valve there and then let go.
      drawn = env.task.initial_angle
      angle = float(env.physics.bind(valve).qpos[0])
      error = (angle - drawn + np.pi) % (2 * np.pi) - np.pi
      assert abs(error) < np.deg2rad(5)
      torque = _torque(env.virtual_bus)
      assert not torque[50]
      assert all(torque[i] for i in env.robot.joint_ids)
      joints = env.physics.bind(env.task.robot.joints).qpos
      goal = env.physics.bind(env.task.robot.actuators).ctrl
      assert np.abs(joints - goal).max() < np.deg2rad(5)
  finally:
    env.close()


@pytest.mark.slow
def test_stuck_finger_retries_disentangles_then_fails_naming_it(monkeypatch):
  torque_seen = []
  original = sim_robot.SimulatedRobot.on_write

  def stuck_motor_21(self, servos, ids):
    # Motor 21 (a middle joint) takes its goals but is stuck at joint angle
    # 0 whatever it is told; the reset pose wants -pi/3.
    torque_seen.append(servos[21].torque_enabled)
    original(self, servos, ids)
    actuator = self._motors[21][3]  # noqa: SLF001
    self._data.ctrl[actuator] = 0.0  # noqa: SLF001

  monkeypatch.setattr(sim_robot.SimulatedRobot, 'on_write', stuck_motor_21)
  env = suite.load(
    'dclaw', 'turn_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  try:
    with pytest.raises(resets.ResetError, match=r'\[21\]') as error:
      env.reset()
    assert error.value.motor_ids == (21,)
    assert not any(_torque(env.virtual_bus).values())  # Released.
    # Between tries the disentangling sequence switched the claw off and on.
    assert False in torque_seen and True in torque_seen
  finally:
    env.close()


def test_claw_reset_pose_beyond_the_configured_limits_starts_at_them(caplog):
  # Turn Fixed's reset pose bends the middle joints to -pi/3; this owner
  # allows FFJ11 no further than -0.8 rad. The reset says so and moves the
  # finger to -0.8, rather than retry, disentangle and fail blaming a stuck
  # finger.
  env = _with_limits('dclaw', 'turn_fixed', {'FFJ11': (-0.8, 0.0)})
  try:
    with caplog.at_level('WARNING'):
      env.reset()
    assert (
      'reset: joint FFJ11 starts at -0.800 rad, the limit of its goals, not '
      'at the -1.047 rad the task drew' in caplog.text
    )
    assert 'reset attempt' not in caplog.text
    joints = env.physics.bind(env.task.robot.joints).qpos
    assert abs(joints[1] + 0.8) < np.deg2rad(5)
  finally:
    env.close()


@pytest.mark.slow
def test_manual_reset_releases_the_motors_while_the_person_works():
  seen = []

  class Person:
    env = None

    def __call__(self, message):
      seen.append((message, dict(_torque(self.env.virtual_bus))))

  person = Person()
  procedure = resets.ManualReset(wait=person)
  env = suite.load(
    'dclaw',
    'pose_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', reset=procedure),
  )
  person.env = env
  try:
    env.reset()
    ((message, torque),) = seen
    assert 'press Enter' in message
    assert not any(torque.values())
    assert all(_torque(env.virtual_bus)[i] for i in env.robot.joint_ids)
  finally:
    env.close()


def test_reset_choices_are_checked():
  with pytest.raises(ValueError, match="unknown reset 'bounce'"):
    suite.load(
      'dclaw', 'pose_fixed', robot=suite.RobotOptions('virtual', reset='bounce')
    )


def test_a_robot_without_a_scripted_reset_is_named():
  with pytest.raises(ValueError, match="robot 'dhand' has no scripted reset"):
    resets.make('scripted', None, 'dhand')
  with pytest.raises(ValueError, match='needs the torso pose'):
    resets.make('scripted', None, 'dkitty')


def _guide_ticks(angle):
  guide = config_lib.default('dclaw').auxiliary_motor('guide')
  return round(guide.to_motor(angle) / table.RADIANS_PER_TICK)


@pytest.mark.slow
def test_guide_motor_shows_the_moving_goal():
  env = suite.load(
    'dclaw',
    'screw_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', guide='show'),
  )
  try:
    env.reset()
    bus = env.virtual_bus
    assert bus.servo(60).torque_enabled  # Held to show the goal.
    for _ in range(5):
      # Each step sends the goal the agent saw with its action.
      shown = (env.task.goal + np.pi) % (2 * np.pi) - np.pi
      env.step(np.zeros(9))
      env.robot.client.ping(60)  # The goal write has no reply: sync.
      assert bus.goal_positions()[60] == _guide_ticks(shown)
    assert env.task.goal > 0.2  # Screw's goal moved at 0.5 rad/s.
  finally:
    env.close()


@pytest.mark.slow
def test_interactive_mode_takes_the_goal_from_the_guide():
  env = suite.load(
    'dclaw',
    'turn_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', guide='interactive'),
  )
  try:
    env.reset()
    bus = env.virtual_bus
    assert not bus.servo(60).torque_enabled  # Released for the person.
    bus.servo(60).set_present(_guide_ticks(1.0))  # A person turns it.
    timestep = env.step(np.zeros(9))
    assert env.task.goal == pytest.approx(1.0, abs=2e-3)
    valve = float(env.physics.bind(env.task.valve.hinge).qpos[0])
    assert timestep.observation['target_error'][0] == pytest.approx(
      1.0 - valve, abs=2e-3
    )
  finally:
    env.close()


def test_the_guide_is_the_robots_option_not_the_tasks():
  with pytest.raises(ValueError, match='interactive'):
    suite.load('dclaw', 'turn_fixed', task_kwargs={'interactive': True})


def test_guide_needs_a_task_with_a_goal_angle():
  with pytest.raises(ValueError, match='no goal angle'):
    suite.load(
      'dclaw', 'pose_fixed', robot=suite.RobotOptions('virtual', guide='show')
    )


def test_unknown_guide_mode_is_rejected():
  with pytest.raises(ValueError, match='guide must be one of'):
    suite.load(
      'dclaw', 'turn_fixed', robot=suite.RobotOptions('virtual', guide='on')
    )


@pytest.mark.slow
def test_dkitty_stand_up_sequence_runs_and_ends_upright(monkeypatch):
  after_stand_up = []
  original = resets.DKittyScriptedReset._stand_up

  def spy(self, robot, clock):
    original(self, robot, clock)
    after_stand_up.append(resets.upright_and_height(self._torso))  # noqa: SLF001

  monkeypatch.setattr(resets.DKittyScriptedReset, '_stand_up', spy)
  # The torso comes from a tracker fed with the simulated torso.
  holder = {'now': 0.0}

  def poses():
    holder['now'] += 0.01
    position, quaternion, _, _ = holder['env'].simulated_robot.torso_pose()
    return {'torso': tracking.Pose(position, quaternion, holder['now'])}

  tracker = tracking.TorsoTracker(
    tracking.SimulatedSource(poses), 'torso', clock=lambda: holder['now']
  )
  env = suite.load(
    'dkitty',
    'stand_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', reset='scripted', tracker=tracker),
  )
  holder['env'] = env
  try:
    env.reset()
    # The robot started crouched (not standing): the tuck and stand-up
    # sequence ran, left it upright at standing height, and the task's
    # crouch was then moved to.
    assert after_stand_up
    upright, height = after_stand_up[-1]
    assert upright > 0.9 and abs(height - 0.30) < 0.05
    joints = env.physics.bind(env.task.robot.joints).qpos
    assert (
      np.abs(joints - env.physics.bind(env.task.robot.actuators).ctrl).max()
      < 0.3
    )
  finally:
    env.close()


def test_dkitty_stand_up_beyond_the_configured_limits_is_refused_unmoved():
  # The stand-up goes beyond the action ranges on purpose, never beyond the
  # limits an owner wrote into the robot's configuration.
  env = _with_limits(
    'dkitty', 'stand_fixed', {'FRJ11': (-0.1, 0.1)}, reset='scripted'
  )
  try:
    goals = env.virtual_bus.goal_positions()
    with pytest.raises(
      resets.ResetError,
      match=r'scripted reset cannot run: joint FRJ11 \(motor 11\) would go '
      r'to [+-]\d\.\d{3} rad, outside its configured limits '
      r'\[-0\.100, \+0\.100\]',
    ):
      env.reset()
    assert not any(_torque(env.virtual_bus).values())
    assert env.virtual_bus.goal_positions() == goals
    with pytest.raises(ValueError, match='outside its configured limits'):
      env.robot.write_reset_goals([11], [1.0])
    assert env.virtual_bus.goal_positions() == goals
  finally:
    env.close()


@pytest.mark.slow
def test_dkitty_that_cannot_get_up_fails_clearly_and_is_released():
  env = suite.load(
    'dkitty',
    'walk_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', reset='scripted'),
  )
  try:
    env.reset()
    simulation = env.simulated_robot
    physics = simulation.physics
    root = int(physics.bind(env.task.root_joint).qposadr)
    physics.data.qpos[root : root + 7] = [
      0,
      0,
      0.15,
      0,
      1,
      0,
      0,
    ]  # Upside down.
    simulation.advance(1.0)
    with pytest.raises(resets.ResetError, match='did not stand up'):
      env.reset()
    assert not any(_torque(env.virtual_bus).values())
  finally:
    env.close()


@pytest.mark.slow
def test_tracker_gives_the_torso_calibrates_at_reset_and_moves_the_target():
  holder = {'now': 0.0}

  def poses():
    # A motion-capture stream of the virtual robot's torso (in a frame
    # shifted by (5, -2) m) and of a target 1.5 m from the torso.
    holder['now'] += 0.1
    position, quaternion, _, _ = holder['env'].simulated_robot.torso_pose()
    shift = np.array([5.0, -2.0, 0.0])
    return {
      'torso': tracking.Pose(position + shift, quaternion, holder['now']),
      'goal': tracking.Pose(
        position + shift + [1.5, 0, 0], [1, 0, 0, 0], holder['now']
      ),
    }

  tracker = tracking.TorsoTracker(
    tracking.SimulatedSource(poses), 'torso', target_body='goal',
    clock=lambda: holder['now'],
  )  # fmt: skip
  env = suite.load(
    'dkitty',
    'walk_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', tracker=tracker),
  )
  holder['env'] = env
  try:
    timestep = env.reset()
    # Calibrated at reset: the torso is at robel_dm's origin, whatever the
    # tracker's frame; the target is where the tracker sees it.
    assert timestep.observation['root_pos'] == pytest.approx(
      np.zeros(3), abs=0.01
    )
    timestep = env.step(env.task.normalize_joint_targets(np.zeros(12)))
    assert env.task.target == pytest.approx([1.5, 0.0], abs=0.02)
    assert timestep.observation['target_error'] == pytest.approx(
      [1.5, 0.0], abs=0.05
    )
  finally:
    env.close()


def _knock_over(env) -> None:
  simulation = env.simulated_robot
  physics = simulation.physics
  root = int(physics.bind(env.task.root_joint).qposadr)
  physics.data.qpos[root : root + 7] = [0, 0, 0.15, 0, 1, 0, 0]  # On its back.
  simulation.advance(1.0)


@pytest.mark.slow
def test_a_fallen_virtual_dkitty_is_stood_up_by_the_simulated_person():
  # The reset the D'Kitty declares for episodes in a row (the zoo's).
  reset = robots.ROBOTS['dkitty'].unattended_reset
  env = suite.load(
    'dkitty',
    'stand_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', reset=reset),
  )
  try:
    env.reset()
    _, start_height = resets.upright_and_height(env.simulated_robot.torso_pose)
    _knock_over(env)
    assert resets.upright_and_height(env.simulated_robot.torso_pose)[0] < 0
    timestep = env.reset()
    upright, height = resets.upright_and_height(env.simulated_robot.torso_pose)
    assert upright > 0.99
    assert height == pytest.approx(start_height, abs=0.02)
    assert timestep.observation['upright'] > 0.99
    assert all(_torque(env.virtual_bus).values())
  finally:
    env.close()


@pytest.mark.slow
def test_dkitty_manual_reset_waits_until_the_robot_is_stood_up():
  env = suite.load(
    'dkitty',
    'walk_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', reset='manual'),
  )
  try:
    env.reset()
    _knock_over(env)
    # A person who does not come: the reset of a robot with a tracker.
    nobody = resets.ManualReset(
      torso_source=env.simulated_robot.torso_pose, timeout=5.0
    )
    clock = clock_lib.SimulatedClock(env.simulated_robot)
    with pytest.raises(resets.ResetError, match='not stood up within 5.0 s'):
      nobody(env.robot, clock, np.zeros(12), {})
  finally:
    env.close()


def test_robot_options_are_one_checked_value():
  with pytest.raises(ValueError, match='guide must be one of'):
    suite.RobotOptions('virtual', guide='point')
  with pytest.raises(ValueError, match='device_path must name a bus'):
    suite.RobotOptions('')
  options = suite.RobotOptions('virtual', reset='move')
  with pytest.raises(dataclasses.FrozenInstanceError):
    options.reset = 'manual'
