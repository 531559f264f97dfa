"""Faults that once left motors torqued, or readings wrong (issue 17).

Exit signals while a worker thread drives the robot, a torque-off that a
motor misses, a goal lost again when it is sent again, and late replies on
every read path. Faults are injected at a known packet: into the virtual
bus (its `faults`, or a late reply put ahead of the reply to one packet),
in-process on `device_path='virtual'` and in lockstep with the bus; the
signal cases run a child Python against a standalone virtual bus
(test_robot_safety's helpers).
"""

import contextlib
import logging
import signal
import subprocess
import sys
import textwrap

import child_signals
import numpy as np
import pytest

from robel_dm.hardware import config as config_lib
from robel_dm.hardware import shutdown
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Instruction

# Without the hardware extra these tests are skipped, not errors.
sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
# Its fixtures and helpers need the extra too.
import test_robot_safety as safety  # noqa: E402

# test_robot_safety's fixtures, here too, and its helpers. In-process tests
# run in `lockstep` with the bus, so that only the injected faults fail.
lockstep = safety.lockstep
claw = safety.claw
standalone_bus = safety.standalone_bus
_child = safety._child  # noqa: SLF001
_torque = safety.read_torque
_wait_for_line = safety._wait_for_line  # noqa: SLF001
_STARTUP_TIMEOUT_S = safety._STARTUP_TIMEOUT_S  # noqa: SLF001

_CLAW_IDS = [m.id for m in config_lib.default('dclaw').joints]
_EXIT_SIGNALS = [signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT]


def _read_torque(device_path: str, ids, attempts: int = 3) -> dict[int, int]:
  """Torque Enable of each motor (`_torque`), read again if a loaded
  machine made the bus (in its own process) miss the SDK's deadline."""
  for _ in range(attempts - 1):
    with contextlib.suppress(AssertionError):
      return _torque(device_path, ids)
  return _torque(device_path, ids)


def _device_path(env) -> str:
  return env.robot.client._device_path  # noqa: SLF001


# --- Exit signals while a worker thread drives the robot ----------------------

# The main thread imports the suite, starts the worker and only waits (the
# repro of the issue: nothing but `from robel_dm import suite` in it).
_DRIVE_FROM_A_WORKER = """
import threading
{main_thread_import}

def drive():
  robot = suite.RobotOptions(DEVICE, reset='move')
  env = suite.load('dclaw', 'turn_fixed', robot=robot)
  env.reset()
  print('stepping', flush=True)
  rng = np.random.default_rng(0)
  while True:
    if env.step(rng.uniform(-0.3, 0.3, 9)).last():
      env.reset()

worker = threading.Thread(target=drive, name='robot')
worker.start()
worker.join()
"""


@pytest.mark.slow
@pytest.mark.parametrize('signum', _EXIT_SIGNALS, ids=lambda s: s.name)
def test_an_exit_signal_releases_a_robot_driven_from_a_worker_thread(
  standalone_bus, signum
):
  device_path, _ = standalone_bus
  child = _child(
    device_path,
    _DRIVE_FROM_A_WORKER.format(main_thread_import=''),
  )
  try:
    line = _wait_for_line(child.stdout, _STARTUP_TIMEOUT_S)
    assert line == 'stepping', child.communicate(timeout=60)[1]
    child.send_signal(signum)
    _, errors = child.communicate(timeout=60)
  finally:
    if child.poll() is None:
      child.kill()
      child.wait()
  ids = _CLAW_IDS + [50]  # And the valve's encoder, which turn reads.
  assert _read_torque(device_path, ids) == dict.fromkeys(ids, 0), errors
  assert child.returncode == 128 + signum, errors
  assert 'will not release' not in errors


@pytest.mark.slow
def test_after_an_exit_signal_released_the_robot_it_sends_nothing_more(
  lockstep, claw, monkeypatch
):
  # What the handler does (a real signal here would end the test run): the
  # thread that drives the robot then gets an error naming the signal.
  bus = claw.virtual_bus
  monkeypatch.setattr(shutdown, '_EXIT_SIGNAL', [signal.SIGTERM])
  shutdown.release_all()
  assert not any(s.torque_enabled for s in bus.servos)
  packets = bus.stats['packets']
  for attempt in (lambda: claw.step(np.zeros(9)), claw.reset):
    with pytest.raises(dynamixel.DynamixelError, match='released on SIGTERM'):
      attempt()
  assert bus.stats['packets'] == packets
  assert not any(s.torque_enabled for s in bus.servos)


@pytest.mark.slow
def test_connecting_from_a_worker_thread_warns_when_signals_cannot_release(
  standalone_bus,
):
  device_path, _ = standalone_bus
  # Nothing of robel_dm is imported in the main thread: the worker's import
  # is the first, and no handler can be installed from there.
  code = textwrap.dedent(f"""
    import threading
    def drive():
      from robel_dm import suite
      robot = suite.RobotOptions({device_path!r})
      suite.load('dclaw', 'pose_fixed', robot=robot).close()
      suite.load('dclaw', 'pose_fixed', robot=robot).close()
    worker = threading.Thread(target=drive, name='robot')
    worker.start()
    worker.join()
  """)
  child = subprocess.Popen(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-c', code],
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )
  _, errors = child.communicate(timeout=120)
  assert child.returncode == 0, errors
  warning = (
    'SIGTERM, SIGHUP, SIGQUIT will not release the torque of the motors '
    "connected from thread 'robot'"
  )
  assert errors.count(warning) == 1, errors
  assert 'import robel_dm.hardware.shutdown in the main thread' in errors


@pytest.mark.slow
@pytest.mark.parametrize('signum', _EXIT_SIGNALS, ids=lambda s: s.name)
def test_without_a_robot_an_exit_signal_acts_as_its_default(signum):
  code = textwrap.dedent(f"""
    import os, signal, time
    from robel_dm.hardware import shutdown
    # Installed by the main thread's import, before any robot connects.
    assert signal.getsignal({int(signum)}) is not signal.SIG_DFL
    os.kill(os.getpid(), {int(signum)})
    time.sleep(30)
  """)
  child = subprocess.run(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-c', code],
    capture_output=True,
    text=True,
    timeout=60,
  )
  assert child.returncode == -signum, child.stderr  # Killed by the signal.


# --- Torque-off retried -------------------------------------------------------


@pytest.mark.slow
def test_a_motor_that_misses_two_packets_is_still_released(lockstep, claw):
  bus = claw.virtual_bus
  assert bus.servo(22).torque_enabled
  # It misses the broadcast torque-off and the first confirmation.
  bus.faults.mute_next(22, 2)
  claw.close()
  assert not any(s.torque_enabled for s in bus.servos)
  assert not bus.faults.mute


@pytest.mark.slow
def test_motors_that_cannot_be_released_are_named_in_one_error_line(
  lockstep, claw, caplog
):
  bus = claw.virtual_bus
  for motor_id in (21, 22):
    bus.faults.set_absent(motor_id)
  with caplog.at_level(logging.ERROR):
    claw.close()
  errors = [
    r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR
  ]
  assert len(errors) == 1, errors
  assert 'motors [21, 22] on ' in errors[0]
  assert 'did not confirm their torque off' in errors[0]
  assert not any(
    s.torque_enabled for s in bus.servos if s.motor_id not in (21, 22)
  )


@pytest.mark.slow
def test_motors_that_miss_the_release_are_asked_again_together(
  lockstep, claw, monkeypatch
):
  # One window for all: a gone motor does not make the others wait their
  # turn (a release with several motors unplugged takes 0.5 s, not 0.5 s
  # each).
  bus = claw.virtual_bus
  asked = []
  handle = bus.handle

  def recording(packet, baud_rate=None):
    if packet.id in (21, 31) and packet.params == bytes(
      [table.TORQUE_ENABLE.address, 0, 0]
    ):
      asked.append(packet.id)
    return handle(packet, baud_rate)

  monkeypatch.setattr(bus, 'handle', recording)
  for motor_id in (21, 31):
    bus.faults.set_absent(motor_id)
  claw.close()
  assert asked[:4] == [21, 31, 21, 31], asked
  assert abs(asked.count(21) - asked.count(31)) <= 1, asked


# --- Re-sent goals read back --------------------------------------------------


def test_a_goal_sent_again_is_read_back_before_the_step_returns(
  lockstep, claw, caplog
):
  bus, client = claw.virtual_bus, claw.robot.client
  claw.step(np.full(9, 0.1))
  reads = bus.servo(12).counters[Instruction.READ]
  bus.faults.lose_next_write(12)
  with caplog.at_level(logging.WARNING):
    claw.step(np.full(9, -0.1))  # A new goal for every motor.
  assert 'goal write lost on motors [12]: sent again' in caplog.text
  assert bus.servo(12).counters[Instruction.READ] > reads  # Read back.
  sent = client._sent_goals[client.motor_ids.index(12)]  # noqa: SLF001
  assert bus.servo(12).goal_position == sent


@pytest.mark.slow
def test_a_goal_lost_again_when_sent_again_ends_the_step(lockstep, claw):
  bus = claw.virtual_bus
  claw.step(np.full(9, -0.1))
  bus.faults.lose_next_write(12, 2)  # The step's goal write and its re-send.
  with pytest.raises(
    dynamixel.DynamixelError, match=r'motors \[12\] did not take their goal'
  ) as error:
    claw.step(np.full(9, 0.1))
  assert error.value.motor_ids == (12,)
  assert _device_path(claw) in str(error.value)
  assert not any(s.torque_enabled for s in bus.servos)


# --- Late replies on every read path ------------------------------------------


def _late_reply_ahead_of(monkeypatch, bus, matches, late_reply, times=1):
  """Makes the bus send `late_reply` ahead of its replies to the next `times`
  packets that `matches`; returns [how many are left]."""
  handle, left = bus.handle, [times]

  def handle_after_a_late_reply(packet, baud_rate=None):
    reply = handle(packet, baud_rate)
    if left[0] and matches(packet):
      left[0] -= 1
      return late_reply + reply
    return reply

  monkeypatch.setattr(bus, 'handle', handle_after_a_late_reply)
  return left


def _health_read(packet) -> bool:
  """The sync read of input voltage and temperature (address 144)."""
  address = table.PRESENT_INPUT_VOLTAGE.address.to_bytes(2, 'little')
  return packet.instruction == Instruction.SYNC_READ and (
    packet.params[:2] == address
  )


def _temperature_read(motor_id):
  address = table.PRESENT_TEMPERATURE.address.to_bytes(2, 'little')
  return lambda packet: (
    packet.instruction == Instruction.READ
    and packet.id == motor_id
    and packet.params[:2] == address
  )


# An empty status (a write's reply), and a ping's (model 1040, firmware 46).
_LATE_REPLIES = {
  'empty': protocol.encode_status(10, 0, b''),
  'ping': protocol.encode_status(10, 0, bytes([0x10, 0x04, 46])),
}


@pytest.mark.slow
def test_reset_drains_a_late_reply_ahead_of_its_health_read(
  lockstep, claw, monkeypatch
):
  bus = claw.virtual_bus
  left = _late_reply_ahead_of(
    monkeypatch, bus, _health_read, _LATE_REPLIES['empty']
  )
  claw.reset()  # Read again, not an IndexError.
  assert left == [0]
  assert claw.step(np.zeros(9)).mid()


@pytest.mark.slow
@pytest.mark.parametrize('late_reply', _LATE_REPLIES)
def test_a_late_reply_is_not_taken_for_the_health_read(
  lockstep, claw, monkeypatch, late_reply
):
  bus, robot = claw.virtual_bus, claw.robot
  left = _late_reply_ahead_of(
    monkeypatch, bus, _health_read, _LATE_REPLIES[late_reply]
  )
  robot.check_health(force=True)
  assert left == [0]
  servos = [bus.servo(i) for i in robot.motor_ids]
  np.testing.assert_allclose(
    robot.voltages,
    [s.get(table.PRESENT_INPUT_VOLTAGE) * table.VOLTS_PER_UNIT for s in servos],
  )
  np.testing.assert_array_equal(
    robot.temperatures, [s.get(table.PRESENT_TEMPERATURE) for s in servos]
  )


@pytest.mark.slow
@pytest.mark.parametrize('late_reply', _LATE_REPLIES)
def test_a_late_reply_is_not_taken_for_a_register_read(
  lockstep, claw, monkeypatch, late_reply
):
  bus, client = claw.virtual_bus, claw.robot.client
  left = _late_reply_ahead_of(
    monkeypatch, bus, _temperature_read(10), _LATE_REPLIES[late_reply]
  )
  values = client.read_register(table.PRESENT_TEMPERATURE, [10, 11])
  assert left == [0]
  assert values == {
    i: bus.servo(i).get(table.PRESENT_TEMPERATURE) for i in (10, 11)
  }
  assert claw.step(np.zeros(9)).mid()  # Nothing left behind in the port.


@pytest.mark.slow
def test_late_replies_to_every_health_read_name_the_motor_and_port(
  lockstep, claw, monkeypatch
):
  _late_reply_ahead_of(
    monkeypatch,
    claw.virtual_bus,
    _health_read,
    _LATE_REPLIES['empty'],
    times=1000,
  )
  with pytest.raises(dynamixel.DynamixelError) as error:
    claw.robot.check_health(force=True)
  assert error.value.motor_ids == (10,)
  message = str(error.value)
  assert 'motor 10 answered reading address 144' in message
  assert _device_path(claw) in message
  assert not isinstance(error.value, dynamixel.MissingMotorError)


@pytest.mark.slow
def test_late_replies_to_every_register_read_name_the_motor_and_port(
  lockstep, claw, monkeypatch
):
  _late_reply_ahead_of(
    monkeypatch,
    claw.virtual_bus,
    _temperature_read(10),
    _LATE_REPLIES['ping'],
    times=1000,
  )
  with pytest.raises(dynamixel.DynamixelError) as error:
    claw.robot.client.read_register(table.PRESENT_TEMPERATURE, [10])
  assert error.value.motor_ids == (10,)
  assert 'motor 10 answered reading address 146' in str(error.value)
  assert _device_path(claw) in str(error.value)


@pytest.mark.slow
def test_a_motor_silent_in_the_health_read_is_named_with_the_port(
  lockstep, claw
):
  claw.virtual_bus.faults.set_absent(31)
  with pytest.raises(dynamixel.MissingMotorError) as error:
    claw.robot.check_health(force=True)
  assert error.value.motor_ids == (31,)
  assert f'motors [31] stopped answering on {_device_path(claw)}' in str(
    error.value
  )
