"""A reset brings the robot back after a fault (issue 17).

An error during a step releases the motors, and the environment refuses to
step until it is reset. On a bus that answers again, that reset must bring
the robot back (torque on, goals taken, state read) so that the episode can
go on; on a bus that still fails, it must raise an error naming what
failed and leave every motor's torque off, and a later reset must still
work once the bus is healthy. In-process on `device_path='virtual'`, in
lockstep with the bus (see test_robot_safety), so that only the injected
faults fail.
"""

import numpy as np
import pytest

from robel_dm import suite
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table

# Without the hardware extra these tests are skipped, not errors.
sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
# Its fixtures and helpers need the extra too.
import test_robot_safety as safety  # noqa: E402

# test_robot_safety's fixtures, here too.
lockstep = safety.lockstep
short_timeouts = safety.short_timeouts

# Observations of the robot's joint angles (and velocities), per robot.
_JOINT_OBSERVATIONS = (('claw_qpos', None), ('kitty_qpos', 'kitty_qvel'))
_UNANSWERED = 10**6  # Packets: for as long as the test runs.


@pytest.fixture(
  params=[
    pytest.param(('dkitty', 'stand_fixed', None), marks=pytest.mark.slow),
    ('dclaw', 'turn_fixed', None),  # The scripted reset.
    # Reads before it writes a goal.
    pytest.param(('dclaw', 'turn_fixed', 'move'), marks=pytest.mark.slow),
  ],
  ids=lambda task: '-'.join(filter(None, task)),
)
def robot(request, lockstep):
  """A task on an in-process virtual bus, reset; closed afterwards."""
  del lockstep  # Active from before the bus starts.
  domain, task, reset = request.param
  env = suite.load(
    domain, task, seed=0, robot=suite.RobotOptions('virtual', reset=reset)
  )
  try:
    env.reset()
    yield env
  finally:
    env.close()


def _hold(env) -> np.ndarray:
  """The action that holds the robot's joints where they are."""
  joints = env.physics.bind(env.task.robot.joints).qpos
  return env.task.normalize_joint_targets(joints)


def _torque(env) -> dict[int, bool]:
  return {s.motor_id: s.torque_enabled for s in env.virtual_bus.servos}


def _release_on_lost_goals(env) -> None:
  """The issue's fault: motor 12's goal writes are lost until the client
  gives up on them; the step raises and the robot is released."""
  env.virtual_bus.faults.lose_next_write(12, 3)
  hold = _hold(env)
  with pytest.raises(dynamixel.DynamixelError, match=r'motors \[12\] did'):
    # New goals (a lost write of the goal a motor holds goes unnoticed).
    env.step(np.clip(hold + 0.05, -1, 1))
    env.step(np.clip(hold - 0.05, -1, 1))
  assert not any(_torque(env).values())


def _assert_observes_the_servos(env, timestep) -> None:
  """The timestep's joint state is what the servos report (calibrated)."""
  bus, motors = env.virtual_bus, env.robot_config.joints
  ((positions, velocities),) = [
    keys for keys in _JOINT_OBSERVATIONS if keys[0] in timestep.observation
  ]
  angles = [
    m.to_joint(bus.servo(m.id).present_position * table.RADIANS_PER_TICK)
    for m in motors
  ]
  np.testing.assert_allclose(timestep.observation[positions], angles)
  if velocities is not None:
    speeds = [
      m.scale
      * bus.servo(m.id).present_velocity
      * table.RADIANS_PER_SECOND_PER_UNIT
      for m in motors
    ]
    np.testing.assert_allclose(
      timestep.observation[velocities], speeds, atol=1e-12
    )


def _assert_runs_an_episode(env) -> None:
  """A reset, then 10 steps, each observing the servos' state."""
  timestep = env.reset()
  assert timestep.first()
  joints = env.robot.joint_ids
  assert all(_torque(env)[i] for i in joints)
  _assert_observes_the_servos(env, timestep)
  action = _hold(env)
  for _ in range(10):
    timestep = env.step(action)
    assert timestep.mid()
    _assert_observes_the_servos(env, timestep)
  assert all(_torque(env)[i] for i in joints)


def test_reset_brings_the_robot_back_after_lost_goal_writes(robot):
  _release_on_lost_goals(robot)
  robot.virtual_bus.faults.clear()
  with pytest.raises(dynamixel.RobotReleasedError, match='reset'):
    robot.step(_hold(robot))
  _assert_runs_an_episode(robot)
  # And again, after a second fault in the same session.
  _release_on_lost_goals(robot)
  robot.virtual_bus.faults.clear()
  _assert_runs_an_episode(robot)


@pytest.mark.slow
@pytest.mark.parametrize(
  'failure, motor_id, message',
  [
    pytest.param('mute', 31, r'motors \[31\] do not', id='muted-motor'),
    pytest.param('corrupt', 22, r'motors \[22\] do not', id='garbled-motor'),
  ],
)
def test_a_reset_on_a_still_failing_bus_raises_and_leaves_torque_off(
  short_timeouts, robot, failure, motor_id, message
):
  _release_on_lost_goals(robot)
  faults = robot.virtual_bus.faults
  faults.clear()
  if failure == 'mute':  # A motor that stopped answering.
    faults.mute_next(motor_id, _UNANSWERED)
  else:  # A motor whose every reply is corrupted.
    faults.corrupt_next(motor_id, _UNANSWERED)
  for _ in range(2):  # As often as it is tried.
    with pytest.raises(dynamixel.DynamixelError, match=message) as error:
      robot.reset()
    assert 'reset could not bring the robot back' in str(error.value)
    assert error.value.motor_ids == (motor_id,)
    assert not any(_torque(robot).values())
    with pytest.raises(dynamixel.RobotReleasedError):
      robot.step(_hold(robot))
  faults.clear()
  _assert_runs_an_episode(robot)
