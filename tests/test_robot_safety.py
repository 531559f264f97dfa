"""How a robot session ends: motors released, faults final, one bus owner.

Cases that involve a process ending run a child Python process against a
standalone virtual bus (its own process, the real dynamixel_sdk), and read
Torque Enable (address 64) back through the SDK after the child is gone.
The others run in-process on `device_path='virtual'`.
"""

import dataclasses
import json
import logging
import select
import signal
import subprocess
import sys
import textwrap
import time

import child_signals
import numpy as np
import pytest

from robel_dm import suite
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import shutdown, virtual
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel.protocol import Instruction

# Without the hardware extra these tests are skipped, not errors.
sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
port_handler = sdk.port_handler

_CLAW_IDS = [m.id for m in config_lib.default('dclaw').joints]
_STARTUP_TIMEOUT_S = 60


@pytest.fixture
def short_timeouts(monkeypatch):
  """A silent motor costs ~6 ms instead of ~34 ms (fault tests only)."""
  monkeypatch.setattr(port_handler, 'LATENCY_TIMER', 2)


def _wait_for(condition, describe, timeout_s: float = 60.0) -> None:
  """Waits until `condition()`; a hang guard (60 s) fails with `describe()`."""
  deadline = time.monotonic() + timeout_s
  while not condition():
    assert time.monotonic() < deadline, describe()
    time.sleep(0.0002)


@pytest.fixture
def lockstep(monkeypatch):
  """The SDK in lockstep with the in-process virtual buses started from now.

  A virtual bus answers from its own thread. The client already waits for
  a bus that is behind before it calls a motor silent (`bus_progress`), but
  only when it expects a reply: a write without one (a sync write, a
  broadcast) returns as soon as its bytes are sent, so a fault injected
  right after it could reach the bus before that write does. In lockstep
  every packet the SDK sends waits until the bus has answered it (the bus
  counts the bytes it has answered, `bytes_in`) and the whole reply
  (`bytes_out`) is readable, so a fault injected between calls hits
  exactly the next packets sent, whatever the load. Request it before any
  fixture that loads a robot.
  """
  servers = {}  # Device path -> the server started on it.
  start = virtual.PtyBusServer.start
  write = sdk.PortHandler.writePort

  def start_and_record(server):
    start(server)
    servers[server.device_path] = server
    return server

  def write_in_lockstep(port, packet):
    server = servers.get(port.port_name)
    if server is None:
      return write(port, packet)
    replied = server.stats['bytes_out']  # The bus is idle: all answered.
    written = write(port, packet)
    sent = port.lockstep_sent = getattr(port, 'lockstep_sent', 0) + written
    _wait_for(
      lambda: server.stats['bytes_in'] >= sent,
      lambda: (
        f'the bus answered {server.stats["bytes_in"]} of the {sent} bytes '
        f'sent (running: {server.running}, errors: {server.errors})'
      ),
    )
    reply = server.stats['bytes_out'] - replied
    _wait_for(
      lambda: port.ser.in_waiting >= reply,
      lambda: f'{port.ser.in_waiting} of {reply} reply bytes readable',
    )
    return written

  monkeypatch.setattr(virtual.PtyBusServer, 'start', start_and_record)
  monkeypatch.setattr(sdk.PortHandler, 'writePort', write_in_lockstep)
  yield
  assert servers, 'no bus started in lockstep: request lockstep first'


@pytest.fixture
def claw():
  """D'Claw Pose on an in-process virtual bus, reset; closed afterwards."""
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  env.reset()
  yield env
  env.close()


def _wait_for_line(stream, timeout: float) -> str:
  ready, _, _ = select.select([stream], [], [], timeout)
  assert ready, 'no output in time'
  return stream.readline().strip()


def _wait_until_stepping(child: subprocess.Popen) -> None:
  """Waits for a `_STEP_FOREVER` child to step; fails with its stderr."""
  line = _wait_for_line(child.stdout, _STARTUP_TIMEOUT_S)
  if line != 'stepping':
    child.kill()
    assert line == 'stepping', child.communicate(timeout=60)[1]


@pytest.fixture
def standalone_bus(monkeypatch):
  """A D'Claw's motors on a virtual bus in its own process; its path.
  This process reads it back with a reply deadline of about 1 s."""
  monkeypatch.setattr(port_handler, 'LATENCY_TIMER', 500)
  process = subprocess.Popen(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-m', 'robel_dm.commands.virtual_bus',
          '--robot=dclaw', '--driver=ideal'],
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )  # fmt: skip
  try:
    yield _wait_for_line(process.stdout, _STARTUP_TIMEOUT_S), process
  finally:
    if process.poll() is None:
      process.send_signal(signal.SIGTERM)
      try:
        process.wait(10)
      except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def read_torque(device_path: str, ids=tuple(_CLAW_IDS)) -> dict[int, int]:
  """Torque Enable of each motor, read through the SDK."""
  port = sdk.PortHandler(device_path)
  assert port.openPort()
  try:
    packets = sdk.PacketHandler(2.0)
    values = {}
    for motor_id in ids:
      value, result, _ = packets.read1ByteTxRx(
        port, motor_id, table.TORQUE_ENABLE.address
      )
      assert result == sdk.COMM_SUCCESS, motor_id
      values[motor_id] = value
    return values
  finally:
    port.closePort()


def _child(device_path: str, body: str) -> subprocess.Popen:
  """Runs `body` in a child Python with DEVICE set; stdout is a pipe."""
  code = (
    'import gc, json, numpy as np\n'
    'import dynamixel_sdk\n'
    'from robel_dm import suite\n'
    # A reply deadline of about 1 s: the bus is another process, and on a
    # loaded machine its healthy replies can miss the SDK's ~34 ms.
    'dynamixel_sdk.port_handler.LATENCY_TIMER = 500\n'
    f'DEVICE = {device_path!r}\n' + textwrap.dedent(body)
  )
  return subprocess.Popen(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-c', code],
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )


_STEP_FOREVER = """
robot = suite.RobotOptions(DEVICE, reset='move')
env = suite.load('dclaw', 'pose_fixed', robot=robot)
env.reset()
print('stepping', flush=True)
rng = np.random.default_rng(0)
while True:
  timestep = env.step(rng.uniform(-0.3, 0.3, 9))
  if timestep.last():
    env.reset()
"""


def _wait_for_port_lock(pid: int) -> None:
  """Waits until process `pid` holds a port's lock (it connected)."""
  deadline = time.monotonic() + _STARTUP_TIMEOUT_S
  while time.monotonic() < deadline:
    with open('/proc/locks') as locks:
      if any(
        line.split()[1] == 'FLOCK' and line.split()[4] == str(pid)
        for line in locks
      ):
        return
    time.sleep(0.05)
  raise AssertionError(f'process {pid} never connected')


def _torque_on_after(child: subprocess.Popen, device_path: str) -> list[int]:
  child.wait(30)
  return [i for i, on in read_torque(device_path).items() if on]


# --- Ends of a session --------------------------------------------------------


@pytest.mark.slow
def test_garbage_collected_environment_releases_its_motors(standalone_bus):
  device_path, _ = standalone_bus
  child = _child(
    device_path,
    """
    import dynamixel_sdk as sdk
    def run():
      env = suite.load('dclaw', 'turn_fixed',
                       robot=suite.RobotOptions(DEVICE, reset='move'))
      env.reset()
      env.step(np.zeros(9))
    run()
    gc.collect()
    # Released already, before exit: read the torque here.
    port = sdk.PortHandler(DEVICE)
    assert port.openPort()
    packets = sdk.PacketHandler(2.0)
    print(json.dumps([packets.read1ByteTxRx(port, i, 64)[0]
                      for i in (10, 11, 12, 20, 21, 22, 30, 31, 32, 50)]))
    port.closePort()
    """,
  )
  output, errors = child.communicate(timeout=60)
  assert child.returncode == 0, errors
  assert json.loads(output.strip().splitlines()[-1]) == [0] * 10
  assert read_torque(device_path, _CLAW_IDS + [50]) == dict.fromkeys(
    _CLAW_IDS + [50], 0
  )


@pytest.mark.slow
@pytest.mark.parametrize('signum', [signal.SIGHUP, signal.SIGQUIT])
def test_hangup_and_quit_release_the_motors(standalone_bus, signum):
  device_path, _ = standalone_bus
  child = _child(device_path, _STEP_FOREVER)
  _wait_until_stepping(child)
  time.sleep(0.3)  # Mid-episode.
  child.send_signal(signum)
  assert _torque_on_after(child, device_path) == []
  assert child.returncode == 128 + signum


@pytest.mark.slow
def test_a_burst_of_ctrl_c_cannot_interrupt_the_release(standalone_bus):
  # Ctrl-C every 2 ms until the program has exited: every release it
  # attempts (on the error, at close, at exit) is hit by signals.
  device_path, _ = standalone_bus
  for _ in range(3):
    child = _child(device_path, _STEP_FOREVER)
    _wait_until_stepping(child)
    time.sleep(0.2)
    deadline = time.monotonic() + 20
    while child.poll() is None and time.monotonic() < deadline:
      child.send_signal(signal.SIGINT)
      time.sleep(0.002)
    assert _torque_on_after(child, device_path) == []


@pytest.mark.slow
def test_every_robot_is_released_whatever_another_release_raises(monkeypatch):
  first = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  second = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  try:
    first.reset()
    second.reset()

    def broken():
      raise ValueError('a bug in a release')

    monkeypatch.setattr(first.robot.client, '_release_all', broken)
    shutdown.release_all()  # What runs at exit.
    assert not any(s.torque_enabled for s in second.virtual_bus.servos)
  finally:
    monkeypatch.undo()
    first.close()
    second.close()


# --- Faults -------------------------------------------------------------------


@pytest.mark.slow
def test_after_a_fault_the_environment_refuses_to_step_until_reset(
  lockstep, short_timeouts, claw
):
  env, bus = claw, claw.virtual_bus
  bus.faults.set_absent(31)
  with pytest.raises(dynamixel.MissingMotorError):
    env.step(np.zeros(9))
  bus.faults.clear()  # The motor is back, but the robot is limp.
  with pytest.raises(dynamixel.RobotReleasedError, match='reset'):
    env.step(np.zeros(9))
  # Released while 31 was away (a vanished motor keeps its torque).
  assert not any(s.torque_enabled for s in bus.servos if s.motor_id != 31)
  env.reset()  # Checks the bus and re-enables the motors.
  assert env.step(np.zeros(9)).mid()
  assert all(bus.servo(i).torque_enabled for i in _CLAW_IDS)


@pytest.mark.slow
@pytest.mark.parametrize('limit', [None, 2500.0])
def test_over_current_stops_the_episode_naming_motor_and_current(limit):
  # A 2 A stall: over the default limit (1.5 A); under a configuration's
  # own 2.5 A, where a 3 A one is not.
  config = config_lib.default('dkitty')
  if limit is not None:
    health = dataclasses.replace(config.health, max_current=limit)
    config = dataclasses.replace(config, health=health)
  env = suite.load(
    'dkitty',
    'stand_fixed',
    seed=0,
    robot=suite.RobotOptions('virtual', robot_config=config),
  )
  bus = env.virtual_bus
  try:
    env.reset()
    unit = table.MODELS[bus.servo(41).model_number][1]  # mA per unit.
    bus.servo(41).inject_current(round(2000 / unit))
    if limit is not None:
      assert env.step(env.task.normalize_joint_targets(np.zeros(12))).mid()
      bus.servo(41).inject_current(round(3000 / unit))
    with pytest.raises(
      dynamixel.MotorFaultError, match=r'over-current on motors \[41\]: \['
    ) as error:
      env.step(env.task.normalize_joint_targets(np.zeros(12)))
    assert error.value.motor_ids == (41,)
    current = float(str(error.value).split(': [')[1].split(']')[0])
    assert current == pytest.approx(2000 if limit is None else 3000, abs=unit)
    assert not any(s.torque_enabled for s in bus.servos)
  finally:
    env.close()


@pytest.mark.slow
def test_a_lost_goal_write_is_noticed_and_sent_again(caplog, claw):
  env, bus = claw, claw.virtual_bus
  env.step(np.full(9, 0.1))
  bus.faults.lose_next_write(22)
  with caplog.at_level(logging.WARNING):
    env.step(np.full(9, -0.1))  # A new goal for every motor.
  assert 'goal write lost on motors [22]' in caplog.text
  env.robot.client.ping(22)  # The resent write has no reply: sync.
  client = env.robot.client
  sent = client._sent_goals[client.motor_ids.index(22)]  # noqa: SLF001
  assert bus.servo(22).goal_position == sent


def test_goal_writes_lost_twice_in_a_row_stop_with_an_error(claw):
  env, bus = claw, claw.virtual_bus
  bus.faults.lose_next_write(22, count=3)  # The step's, the resent, next.
  with pytest.raises(dynamixel.DynamixelError, match=r'motors \[22\] did not'):
    env.step(np.full(9, 0.1))
    env.step(np.full(9, -0.1))
  assert not any(s.torque_enabled for s in bus.servos)


# --- Errors name what failed --------------------------------------------------


@pytest.mark.slow
def test_corrupted_replies_blame_the_motor_that_sent_them(
  lockstep, short_timeouts, claw
):
  env, bus = claw, claw.virtual_bus
  reads = bus.servo(22).counters[Instruction.SYNC_READ]
  bus.faults.corrupt_next(22, count=3)  # Every attempt of one read.
  with pytest.raises(dynamixel.DynamixelError) as error:
    env.step(np.zeros(9))
  assert error.value.motor_ids == (22,)
  assert 'motor 22 answered with corrupted replies' in str(error.value)
  assert not isinstance(error.value, dynamixel.MissingMotorError)
  # The three corrupted replies were those to the state read's 3 attempts.
  assert bus.servo(22).counters[Instruction.SYNC_READ] == reads + 3
  assert not bus.faults.corrupt_crc


@pytest.mark.slow
def test_a_late_reply_is_not_taken_for_a_motors_state(claw, monkeypatch):
  # A ping that timed out can be answered late; its reply then waits in the
  # port and the next state read takes it for motor 10's (3 bytes, not 20).
  from robel_dm.hardware.dynamixel import protocol  # noqa: PLC0415

  late_ping_reply = protocol.encode_status(10, 0, bytes([0xE8, 0x03, 0x2D]))
  pending = []
  read_port, tx_rx = sdk.PortHandler.readPort, sdk.GroupSyncRead.txRxPacket

  def read_with_late_reply(port, length):
    return pending.pop() if pending else read_port(port, length)

  def state_read_after_late_reply(reader):
    if reader.data_length == table.STATE_BLOCK_SIZE and not armed:
      armed.append(True)
      pending.append(late_ping_reply)
    return tx_rx(reader)

  armed = []
  monkeypatch.setattr(sdk.PortHandler, 'readPort', read_with_late_reply)
  monkeypatch.setattr(
    sdk.GroupSyncRead, 'txRxPacket', state_read_after_late_reply
  )
  timestep = claw.step(np.zeros(9))  # Read again, not a crash.
  assert armed and not pending
  np.testing.assert_allclose(
    timestep.observation['qpos'], claw.robot.positions[:9]
  )
  claw.step(np.zeros(9))


@pytest.mark.slow
def test_a_motor_with_a_bad_checksum_is_not_called_silent(
  lockstep, short_timeouts, claw
):
  env, bus = claw, claw.virtual_bus
  bus.faults.corrupt_next(31, count=1000)
  with pytest.raises(dynamixel.DynamixelError, match='corrupted') as error:
    env.step(np.zeros(9))
  assert error.value.motor_ids == (31,)
  assert 'stopped answering' not in str(error.value)


@pytest.mark.slow
def test_a_silent_bus_is_named_as_such_after_one_ping_per_motor(claw):
  env, bus = claw, claw.virtual_bus
  env.step(np.zeros(9))
  for servo in bus.servos:
    bus.faults.set_absent(servo.motor_id)
  packets = bus.stats['packets']
  with pytest.raises(dynamixel.MissingMotorError) as error:
    env.step(np.zeros(9))
  assert 'no motor answers on' in str(error.value)
  assert 'check power and cable' in str(error.value)
  assert sorted(error.value.motor_ids) == _CLAW_IDS
  # Bounded work: the goal write, the in-process clock's sync ping, the
  # read and its 2 retries, one ping per motor, and the broadcast release
  # (no per-motor retries on a silent bus, which took seconds).
  assert bus.stats['packets'] - packets <= 1 + 1 + 3 + len(_CLAW_IDS) + 1


# --- One owner per bus --------------------------------------------------------


@pytest.mark.slow
def test_a_second_environment_on_the_same_port_is_refused():
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  try:
    path = env.robot.client._device_path  # noqa: SLF001
    other = dynamixel.DynamixelClient(path, _CLAW_IDS)
    with pytest.raises(dynamixel.PortBusyError, match='this process'):
      other.connect()
    assert not other.is_connected
  finally:
    env.close()


@pytest.mark.slow
def test_a_second_process_on_the_same_port_is_refused(standalone_bus):
  device_path, _ = standalone_bus
  child = _child(device_path, _STEP_FOREVER)
  try:
    _wait_until_stepping(child)
    client = dynamixel.DynamixelClient(device_path, _CLAW_IDS)
    with pytest.raises(dynamixel.PortBusyError, match=rf'pid {child.pid}'):
      client.connect()
  finally:
    child.send_signal(signal.SIGTERM)
    child.wait(30)


@pytest.mark.slow
def test_a_vanished_port_is_named_and_the_command_line_says_so(standalone_bus):
  device_path, bus_process = standalone_bus
  evaluation = subprocess.Popen(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-m', 'robel_dm.commands.evaluate', '--domain=dclaw',
     '--task=pose_fixed', '--episodes=1000', f'--device_path={device_path}',
     '--reset=move'],
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )  # fmt: skip
  _wait_for_port_lock(evaluation.pid)  # Connected.
  time.sleep(1.0)  # Stepping, in real time.
  bus_process.kill()  # The bus vanishes, as if unplugged.
  _, errors = evaluation.communicate(timeout=60)
  assert evaluation.returncode == 2, errors
  assert 'Traceback' not in errors, errors
  lines = [line for line in errors.splitlines() if line.startswith('error:')]
  assert len(lines) == 1 and device_path in lines[0], errors


# --- Validation ---------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize('time_limit', [float('nan'), 0.0, -1.0])
def test_bad_time_limits_are_rejected(time_limit):
  with pytest.raises(ValueError, match='time_limit'):
    suite.load('dclaw', 'pose_fixed', time_limit=time_limit)


def test_complex_actions_are_rejected():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  env.reset()
  with pytest.raises(ValueError, match='real numbers'):
    env.step(np.zeros(9) + 0.1j)


def test_a_closed_environment_closes_again_quietly_and_never_steps():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  env.reset()
  env.close()
  env.close()
  with pytest.raises(RuntimeError, match='closed'):
    env.step(np.zeros(9))
  with pytest.raises(RuntimeError, match='closed'):
    env.reset()
