"""The hardware layer end to end: real dynamixel_sdk, virtual servo bus.

Every environment here is
`suite.load(..., robot=suite.RobotOptions('virtual'))`: the task runs on
`HardwarePhysics` through the unmodified SDK and an in-process virtual bus
whose motors a MuJoCo simulation drives in simulated time.
"""

import dataclasses
import json
import math
import pathlib
import time

import numpy as np
import pytest

from robel_dm import evaluation, suite
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import environment as hardware_env
from robel_dm.hardware import virtual
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table

# Without the hardware extra these tests are skipped, not errors.
sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
# Its fixtures and helpers need the extra too.
import test_robot_safety as safety  # noqa: E402

port_handler = sdk.port_handler

# A virtual-bus episode replays a simulated one within these tolerances on
# every entry of the agent observation (rad, rad/s, m or unitless). Sources
# of difference: angles quantized to 2 pi / 4096 rad and velocities to
# 0.024 rad/s on the bus; and the reset, which on the bus is a real move that
# leaves joints sagging under gravity (up to 0.06 rad on the claw's middle
# joints) where simulation places them exactly. Measured maxima over 30
# steps: D'Claw 0.003 (pose) to 0.058 (turn); D'Kitty 0.025 rad in joint
# angles and 0.11 rad/s in joint velocities (stand).
_TRACKING_TOLERANCE = {'dclaw': 0.1, 'dkitty': 0.25}

# The current safety counter counts the joint motors drawing more than this,
# mA: ROBEL's D'Claw limit (docs/robel_reference.md section 2.3), and
# robel_dm's D'Kitty limit (1 A; ROBEL defines the counters for the D'Claw
# only).
_SAFE_CURRENT = {'dclaw': 200.0, 'dkitty': 1000.0}
_SAFETY_TASKS = [('dclaw', 'pose_fixed'), ('dkitty', 'stand_fixed')]

# test_robot_safety's fixture, here too.
lockstep = safety.lockstep


@pytest.fixture
def short_timeouts(monkeypatch):
  """A missing motor then costs ~6 ms instead of ~34 ms (fault tests only:
  happy paths keep the SDK's margin, which a loaded machine may need)."""
  monkeypatch.setattr(port_handler, 'LATENCY_TIMER', 2)


def _actions(env, steps, seed=0):
  """Random actions; for the D'Kitty small ones around its pose at reset
  (larger ones make it fall and end the episode early)."""
  rng = np.random.default_rng(seed)
  shape = env.action_spec().shape
  if env.task.root_joint is not None:
    joints = env.physics.bind(env.task.robot.joints).qpos
    centre = env.task.normalize_joint_targets(joints)
    return np.clip(centre + rng.uniform(-0.1, 0.1, (steps,) + shape), -1, 1)
  return rng.uniform(-1, 1, (steps,) + shape)


def _torque(bus):
  return {servo.motor_id: servo.torque_enabled for servo in bus.servos}


@pytest.mark.slow
def test_every_task_runs_full_episodes_with_the_simulation_spec(task_id):
  env = suite.load(*task_id, seed=0, robot=suite.RobotOptions('virtual'))
  simulated = suite.load(*task_id, seed=0)
  try:
    assert env.observation_spec() == simulated.observation_spec()
    assert env.action_spec() == simulated.action_spec()
    timestep = env.reset()
    actions = _actions(env, env.task.episode_steps)
    steps = 0
    for action in actions:
      timestep = env.step(action)
      steps += 1
      assert np.all(
        np.isfinite(env.task.flatten_observation(timestep.observation))
      )
      if timestep.last():
        break
    assert timestep.last() and steps == env.task.episode_steps
    assert timestep.discount == 1.0
  finally:
    env.close()


@pytest.mark.slow
@pytest.mark.parametrize(
  'tracked_task',
  [('dclaw', 'pose_fixed'), ('dclaw', 'turn_fixed'), ('dkitty', 'stand_fixed'),
   ('dkitty', 'walk_fixed')],
)  # fmt: skip
def test_virtual_bus_episode_tracks_the_simulation(tracked_task):
  task_id = tracked_task
  env = suite.load(*task_id, seed=0, robot=suite.RobotOptions('virtual'))
  simulated = suite.load(*task_id, seed=0)
  try:
    hardware, sim = env.reset(), simulated.reset()
    tolerance = _TRACKING_TOLERANCE[task_id[0]]
    for action in _actions(simulated, 30):
      hardware, sim = env.step(action), simulated.step(action)
      for key in env.task.agent_observation_keys:
        difference = np.abs(hardware.observation[key] - sim.observation[key])
        if key == 'target_error':  # An angle: compare on the circle.
          difference = np.minimum(difference, 2 * np.pi - difference)
        assert difference.max() < tolerance, key
  finally:
    env.close()


@pytest.mark.slow
def test_safety_counts_measured_currents():
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  try:
    env.reset()
    currents = []
    for action in _actions(env, 10):
      env.step(action)
      currents.append(env.physics.motor_currents.copy())
    assert np.abs(currents).max() > 0  # Measured, not the simulation's 0.
  finally:
    env.close()


def _current_counter(env) -> int:
  """The current safety counter, as the task reports it."""
  return int(env.task.task_observables['safety'](env.physics)[2])


@pytest.mark.slow
@pytest.mark.parametrize(
  'domain_task', _SAFETY_TASKS, ids=lambda task: '-'.join(task)
)
def test_current_counter_on_hand_built_currents(domain_task):
  limit = _SAFE_CURRENT[domain_task[0]]
  env = suite.load(*domain_task, seed=0, robot=suite.RobotOptions('virtual'))
  try:
    env.reset()
    currents = env.physics.motor_currents  # What the task reads, mA.
    joints = len(currents)

    def count(values) -> int:
      currents[:] = values
      env.task._update(env.physics, env.random_state)
      return _current_counter(env)

    just_over, just_under = limit + 0.01, limit - 0.01
    for motor in range(joints):
      one = np.zeros(joints)
      for sign in (1, -1):  # The magnitude counts, whatever the sign.
        one[motor] = sign * just_over
        assert count(one) == 1, (motor, one[motor])
        one[motor] = sign * just_under
        assert count(one) == 0, (motor, one[motor])
        one[motor] = sign * limit  # At the limit is not over it.
        assert count(one) == 0, (motor, one[motor])
      # One motor just over, every other just under.
      mixed = np.full(joints, just_under)
      mixed[motor] = -just_over
      assert count(mixed) == 1, motor
    assert count(np.full(joints, just_over)) == joints
    assert count(np.full(joints, -just_under)) == 0
  finally:
    env.close()


@pytest.mark.slow
@pytest.mark.parametrize(
  'domain_task', _SAFETY_TASKS, ids=lambda task: '-'.join(task)
)
def test_current_counter_counts_currents_the_servos_report(domain_task):
  # Each joint motor in turn reports the smallest current over the limit it
  # can (in whole current units), every other the largest under it; signs
  # alternate. Then all report one over.
  limit = _SAFE_CURRENT[domain_task[0]]
  env = suite.load(*domain_task, seed=0, robot=suite.RobotOptions('virtual'))
  bus = env.virtual_bus
  try:
    env.reset()
    ids = env.robot.joint_ids
    unit = table.MODELS[bus.servo(ids[0]).model_number][1]  # mA per unit.
    over = math.floor(limit / unit) + 1
    under = math.ceil(limit / unit) - 1
    assert under * unit < limit < over * unit  # The test's own data.
    signs = [(-1) ** i for i in range(len(ids))]
    hold = env.task.normalize_joint_targets(
      env.physics.bind(env.task.robot.joints).qpos
    )
    for i, motor_id in enumerate(ids):
      for other, sign in zip(ids, signs, strict=True):
        units = over if other == motor_id else under
        bus.servo(other).inject_current(sign * units)
      timestep = env.step(hold)
      assert timestep.mid()
      assert timestep.observation['safety'][2] == 1, motor_id
      currents = env.physics.motor_currents  # What the task read, mA.
      assert currents[i] == pytest.approx(signs[i] * over * unit)
      assert np.abs(np.delete(currents, i)).max() == pytest.approx(under * unit)
    for motor_id in ids:
      bus.servo(motor_id).inject_current(over)
    assert env.step(hold).observation['safety'][2] == len(ids)
  finally:
    env.close()


def test_torque_is_off_after_close():
  env = suite.load(
    'dclaw', 'turn_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  env.reset()
  env.step(np.zeros(9))
  assert any(_torque(bus).values())
  env.close()
  assert not any(_torque(bus).values())


@pytest.mark.slow
def test_nan_actions_never_reach_the_bus():
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  try:
    env.reset()
    env.step(np.zeros(9))
    bus = env.virtual_bus
    goals = bus.goal_positions()
    packets = bus.stats['packets']
    with pytest.raises(ValueError, match='non-finite'):
      env.step(np.full(9, np.nan))
    assert bus.goal_positions() == goals
    assert bus.stats['packets'] == packets
  finally:
    env.close()


@pytest.mark.slow
def test_an_exception_inside_a_step_releases_the_motors(monkeypatch):
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    env.step(np.zeros(9))

    def fail():
      raise RuntimeError('boom')

    monkeypatch.setattr(env.robot, 'check_health', lambda force=False: fail())
    with pytest.raises(RuntimeError, match='boom'):
      env.step(np.zeros(9))
    assert not any(_torque(bus).values())
  finally:
    env.close()


@pytest.mark.slow
def test_ctrl_c_during_a_step_releases_the_motors(monkeypatch):
  env = suite.load(
    'dclaw', 'turn_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    clock = env.physics.clock

    def interrupted(deadline):
      raise KeyboardInterrupt

    monkeypatch.setattr(clock, 'sleep_until', interrupted)
    with pytest.raises(KeyboardInterrupt):
      env.step(np.zeros(9))
    assert not any(_torque(bus).values())
  finally:
    env.close()


@pytest.mark.slow
def test_overload_stops_the_episode_naming_the_motor():
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    bus.servo(21).inject_hardware_error(0x20)  # Overload: torque cut.
    with pytest.raises(dynamixel.MotorFaultError, match='motor 21: overload'):
      for _ in range(20):  # Health is checked every few steps.
        env.step(np.zeros(9))
    assert not any(_torque(bus).values())
    errors = dict(
      zip(env.robot.motor_ids, env.robot.hardware_errors, strict=True)
    )
    assert errors[21] == 0x20 and not any(errors[i] for i in errors if i != 21)
  finally:
    env.close()


@pytest.mark.slow
def test_a_motor_that_disappears_is_named_and_the_rest_released(
  lockstep, short_timeouts
):
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    bus.faults.set_absent(31)
    with pytest.raises(dynamixel.MissingMotorError, match=r'\[31\]') as error:
      env.step(np.zeros(9))
    assert error.value.motor_ids == (31,)
    torque = _torque(bus)
    assert not any(v for motor_id, v in torque.items() if motor_id != 31)
  finally:
    env.close()


@pytest.mark.slow
def test_a_busy_virtual_bus_is_waited_for_and_a_silent_motor_still_named(
  monkeypatch,
):
  # Each packet takes the simulated bus 0.1 s, three times the SDK's reply
  # deadline, as on a machine busy with other work: its replies come late
  # but come, and a motor that does not answer is still the one named.
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    handle = bus.handle

    def slow(packet, baud_rate):
      time.sleep(0.1)
      return handle(packet, baud_rate)

    monkeypatch.setattr(bus, 'handle', slow)
    assert env.step(np.zeros(9)).mid()
    bus.faults.set_absent(31)
    with pytest.raises(dynamixel.MissingMotorError) as error:
      env.step(np.zeros(9))
    assert error.value.motor_ids == (31,)
  finally:
    env.close()


@pytest.mark.slow
def test_one_corrupted_or_lost_reply_is_retried_transparently(
  lockstep, short_timeouts
):
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    bus.faults.corrupt_next(12)
    first = env.step(np.zeros(9))
    bus.faults.mute_next(22)
    second = env.step(np.zeros(9))
    assert first.mid() and second.mid()
  finally:
    env.close()


@pytest.mark.slow
def test_persistent_corruption_raises_instead_of_returning_stale_data(
  lockstep,
  short_timeouts,
):
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  bus = env.virtual_bus
  try:
    env.reset()
    bus.faults.corrupt_next(12, count=100)
    with pytest.raises(dynamixel.DynamixelError):
      env.step(np.zeros(9))
    assert not any(_torque(bus).values())
  finally:
    env.close()


def test_missing_motor_at_connect_is_named(lockstep, short_timeouts):
  config = config_lib.default('dclaw')
  servos = virtual.make_servos(
    [i for i in virtual.robot_motor_ids(config) if i != 22]
  )
  with virtual.PtyBusServer(virtual.Bus(servos)) as server:
    client = dynamixel.DynamixelClient(server.device_path, config.joint_ids)
    with pytest.raises(dynamixel.MissingMotorError, match=r'\[22\]'):
      client.connect()
    assert not client.is_connected


def test_missing_device_gives_a_clear_error():
  with pytest.raises(dynamixel.DynamixelError, match='cannot open'):
    suite.load(
      'dclaw',
      'pose_fixed',
      robot=suite.RobotOptions('/dev/robel-dm-no-such-port'),
    )


def test_dkitty_on_a_real_bus_needs_a_tracker():
  with pytest.raises(ValueError, match='tracker'):
    suite.load(
      'dkitty', 'stand_fixed', robot=suite.RobotOptions('/dev/ttyUSB0')
    )


def test_client_units_and_signs():
  config = config_lib.default('dclaw')
  servos = virtual.make_servos(config.joint_ids, model_number=1020)
  bus = virtual.Bus(servos)
  with (
    virtual.PtyBusServer(bus) as server,
    dynamixel.DynamixelClient(server.device_path, config.joint_ids) as c,
  ):
    bus.servo(10).set_present(-1024, -10, -57)
    state = c.read_state()
    column = 0
    assert state[2, column] == pytest.approx(-1024 * table.RADIANS_PER_TICK)
    assert state[1, column] == pytest.approx(
      -10 * table.RADIANS_PER_SECOND_PER_UNIT
    )
    assert state[0, column] == pytest.approx(-57 * 2.69)  # W-series unit.
    c.set_torque(config.joint_ids, True)
    c.write_goal_positions(np.full(9, 1.0))
    c.ping(10)  # The sync write has no reply: wait until the bus handled it.
    goal = bus.goal_positions()[10]
    assert goal == round(1.0 / table.RADIANS_PER_TICK)
    with pytest.raises(ValueError, match='non-finite'):
      c.write_goal_positions(np.full(9, np.inf))


def test_robot_configurations_load_and_reject_mistakes(tmp_path):
  default = config_lib.default('dkitty')
  assert default.joints[0].offset == pytest.approx(-1.5 * np.pi)
  path = tmp_path / 'robot.json'
  data = {
    'robot': 'dclaw',
    'joints': [{'name': 'FFJ10', 'id': 10}, {'name': 'FFJ11', 'id': 10}],
  }
  path.write_text(json.dumps(data))
  with pytest.raises(config_lib.ConfigError, match='used twice: \\[10\\]'):
    config_lib.load(path)
  path.write_text('{"robot": "dclaw"}')
  with pytest.raises(config_lib.ConfigError, match='missing "joints"'):
    config_lib.load(path)
  with pytest.raises(config_lib.ConfigError, match='not found'):
    config_lib.load(tmp_path / 'missing.json')


def _with_first_joint(data: dict, **fields) -> dict:
  joints = [dict(data['joints'][0], **fields), *data['joints'][1:]]
  return data | {'joints': joints}


def test_every_malformed_configuration_entry_is_named(tmp_path):
  # A typo or a wrong type must not fall back to a default (a misspelt
  # `limits` would leave the robot its full range) nor fail as a TypeError.
  path = tmp_path / 'robot.json'
  shipped = pathlib.Path(config_lib.__file__).parent / 'configs' / 'dclaw.json'
  data = json.loads(shipped.read_text())
  for bad, message in (
    (data | {'limit': {}}, r"unknown fields \['limit'\]"),
    (data | {'heath': {}}, r"unknown fields \['heath'\]"),
    (data | {'robot': 'banana'}, 'robot must be one of'),
    (data | {'limits': {'FFJ10': 0.3}}, 'limits of FFJ10 must be'),
    (data | {'limits': {'FFJ10': ['a', 'b']}}, 'limits of FFJ10 must be'),
    (data | {'limits': [1]}, 'limits must be an object'),
    (data | {'groups': {'top': 5}}, "group 'top' must be a list"),
    (data | {'baud_rate': '1000000'}, 'is not a Dynamixel rate'),
    (data | {'joints': {}}, 'joints must be a list'),
    (_with_first_joint(data, offset_pi='x'), r'joints\[0\] \(FFJ10\): offset'),
    (_with_first_joint(data, scale=True), 'scale must be 1 or -1'),
    (_with_first_joint(data, id=True), 'id must be an integer'),
    (_with_first_joint(data, optional='false'), 'optional must be true or'),
    (_with_first_joint(data, required_by='turn'), 'required_by must be a list'),
    (
      _with_first_joint(data, calibration=1),
      r"unknown fields \['calibration'\]",
    ),
  ):
    path.write_text(json.dumps(bad))
    with pytest.raises(config_lib.ConfigError, match=message):
      config_lib.load(path)
  path.write_text(json.dumps(_with_first_joint(data, offset_pi=0.5)))
  assert config_lib.load(path).joints[0].offset == pytest.approx(np.pi / 2)


def test_a_configuration_sets_the_health_limits_and_checks_them(tmp_path):
  assert config_lib.default('dclaw').health == config_lib.HealthLimits()
  path = tmp_path / 'robot.json'
  shipped = pathlib.Path(config_lib.__file__).parent / 'configs' / 'dclaw.json'
  data = json.loads(shipped.read_text()) | {
    'health': {'max_current': 2300, 'max_temperature': 75.5}
  }
  path.write_text(json.dumps(data))
  health = config_lib.load(path).health
  assert (health.max_current, health.max_temperature) == (2300.0, 75.5)
  assert health.check_every == config_lib.HealthLimits().check_every
  for bad, message in (
    ({'max_current': -1}, 'health max_current must be a positive number'),
    ({'max_temperature': 'hot'}, 'health max_temperature must be a positive'),
    ({'max_current': True}, 'health max_current must be a positive number'),
    ({'check_every': 5}, "health: unknown fields \\['check_every'\\]"),
    ([1500], 'health must be an object'),
  ):
    path.write_text(json.dumps(data | {'health': bad}))
    with pytest.raises(config_lib.ConfigError, match=message):
      config_lib.load(path)


def test_unknown_device_configuration_mismatch_is_rejected(tmp_path):
  path = tmp_path / 'kitty_as_claw.json'
  kitty = config_lib.default('dkitty')
  path.write_text(
    json.dumps(
      {
        'robot': 'dkitty',
        'joints': [{'name': m.name, 'id': m.id} for m in kitty.joints],
      }
    )
  )
  with pytest.raises(
    config_lib.ConfigError, match='a dkitty configuration, for a dclaw task'
  ):
    hardware_env.make_environment(
      suite.registry.DCLAW['pose_fixed'](),
      domain='dclaw',
      robot=suite.RobotOptions('virtual', robot_config=str(path)),
    )
  # Named a D'Claw, wired as a D'Kitty.
  data = json.loads(path.read_text()) | {'robot': 'dclaw'}
  path.write_text(json.dumps(data))
  with pytest.raises(config_lib.ConfigError, match='do not match'):
    hardware_env.make_environment(
      suite.registry.DCLAW['pose_fixed'](),
      domain='dclaw',
      robot=suite.RobotOptions('virtual', robot_config=str(path)),
    )


@pytest.mark.slow
def test_hardware_reset_moves_to_the_initial_pose_without_simulated_settling():
  env = suite.load(
    'dkitty', 'stand_random', seed=0, robot=suite.RobotOptions('virtual')
  )
  try:
    for _ in range(2):  # The second pose differs from the robot's state.
      env.reset()
      drawn = env.physics.bind(env.task.robot.actuators).ctrl
      joints = env.physics.bind(env.task.robot.joints).qpos
      # The motors were driven to the drawn pose; the simulated settling
      # steps never reached them, and the episode clock starts at 0. Legs
      # carrying the body sag or are blocked by the floor: measured medians
      # 0.002-0.024 rad, worst joint 0.29 rad (0.069 median, and an
      # over-current fault, when settling steps reached the motors).
      error = np.abs(joints - drawn)
      assert np.median(error) < 0.04 and error.max() < 0.35
      assert env.physics.data.time == 0.0
  finally:
    env.close()


@pytest.mark.slow
def test_evaluation_runs_on_the_virtual_bus():
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw',
      'pose_fixed',
      episodes=2,
      policy='reference',
      robot=suite.RobotOptions('virtual'),
    )
  )
  assert results['device_path'] == 'virtual'
  assert results['success_rate'] == 1.0
  assert [record['steps'] for record in results['records']] == [80, 80]


def test_configured_limits_outside_the_action_range_name_the_joint():
  config = dataclasses.replace(
    config_lib.default('dclaw'),
    limits={'FFJ10': (0.6, 0.9), 'MFJ21': (-0.5, 0.5)},
  )
  with pytest.raises(
    config_lib.ConfigError,
    match=r'configured limits of FFJ10 \[0\.6, 0\.9\] lie outside its '
    r'action range \[-0\.480, \+0\.480\] rad',
  ):
    suite.load(
      'dclaw',
      'pose_fixed',
      robot=suite.RobotOptions('virtual', robot_config=config),
    )
