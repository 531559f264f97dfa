"""One owner per serial port: a second opener is refused before it touches
the port, and the port module loads without the `hardware` extra.

The held-port case runs the real `dynamixel_sdk` against the standalone
virtual bus on a pseudo-terminal, which (like real servos) hears only
packets sent at its own line speed.
"""

import os
import select
import signal
import subprocess
import sys
import termios
import textwrap
import time

import pytest

from robel_dm.hardware import config
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol

sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
# Its fixtures and helpers need the extra too.
import test_robot_safety as safety  # noqa: E402

_CLAW_IDS = [joint.id for joint in config.default('dclaw').joints]
_STARTUP_TIMEOUT_S = 60
_OTHER_BAUD_RATE = 57_600
_REPOSITORY = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def standalone_bus(monkeypatch):
  """A D'Claw's motors on a virtual bus in its own process; its path.

  Replies are waited for about 1 s: on a loaded machine the bus process can
  miss the SDK's usual ~34 ms.
  """
  monkeypatch.setattr(sdk.port_handler, 'LATENCY_TIMER', 500)
  process = subprocess.Popen(
    args=[sys.executable, '-m', 'robel_dm.commands.virtual_bus',
          '--robot=dclaw', '--driver=ideal'],
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )  # fmt: skip
  try:
    ready, _, _ = select.select([process.stdout], [], [], _STARTUP_TIMEOUT_S)
    assert ready, 'the virtual bus printed no device path'
    yield process.stdout.readline().strip()
  finally:
    process.send_signal(signal.SIGTERM)
    try:
      process.wait(10)
    except subprocess.TimeoutExpired:
      process.kill()
      process.wait()


def _wait_for_bytes(port, count: int) -> None:
  deadline = time.monotonic() + 30
  while port.getBytesAvailable() < count:
    assert time.monotonic() < deadline, 'the bus did not answer'
    time.sleep(0.001)


def _open_from_another_program(device_path: str) -> str:
  """What a second program that opens the port at 57600 baud is told."""
  code = textwrap.dedent(f"""
    from robel_dm.hardware.dynamixel import client as dynamixel
    client = dynamixel.DynamixelClient(
      {device_path!r}, {_CLAW_IDS!r}, baud_rate={_OTHER_BAUD_RATE})
    try:
      client.connect()
    except dynamixel.PortBusyError as error:
      print(error)
    else:
      print('connected')
  """)
  result = subprocess.run(
    [sys.executable, '-c', code],
    capture_output=True,
    text=True,
    timeout=120,
  )
  assert result.returncode == 0, result.stderr
  return result.stdout.strip()


def test_a_refused_second_program_leaves_the_holders_port_untouched(
  standalone_bus,
):
  device_path = standalone_bus
  holder = dynamixel.DynamixelClient(device_path, _CLAW_IDS)
  holder.connect()
  try:
    holder.set_torque(_CLAW_IDS, True)
    holder.write_goal_positions(holder.read_state()[2] + 0.1)
    holder.read_state()
    # A ping's reply (14 bytes) left waiting in the holder's port.
    port = holder._port  # noqa: SLF001
    motor_id = _CLAW_IDS[0]
    port.writePort(
      protocol.encode_instruction(motor_id, protocol.Instruction.PING)
    )
    _wait_for_bytes(port, 14)
    speed = termios.tcgetattr(port.ser.fileno())[4:6]

    told = _open_from_another_program(device_path)

    assert told.startswith(f'{device_path} is already in use'), told
    assert f'held by pid {os.getpid()}' in told, told
    # Nothing flushed, nothing reconfigured.
    (pending,) = protocol.parse(port.readPort(100))
    assert (pending.id, pending.error) == (motor_id, 0)
    assert pending.data[:2] == holder.models[motor_id].to_bytes(2, 'little')
    assert termios.tcgetattr(port.ser.fileno())[4:6] == speed
    # The holder still drives its motors, at its own speed.
    state = holder.read_state()
    assert state.shape == (3, len(_CLAW_IDS))
    holder.write_goal_positions(state[2] - 0.1)
    holder.read_state()
    torque_on = dict.fromkeys(_CLAW_IDS, 1)
    assert holder.read_register(table.TORQUE_ENABLE) == torque_on
  finally:
    holder.disconnect()
  assert safety.read_torque(device_path) == dict.fromkeys(_CLAW_IDS, 0)


@pytest.mark.slow
@pytest.mark.parametrize(
  'missing',
  [('serial',), ('serial', 'dynamixel_sdk')],
  ids=lambda m: '+'.join(m),
)
def test_without_the_hardware_extra_the_error_names_it(missing):
  code = textwrap.dedent(f"""
    import sys
    for name in {missing!r}:
      sys.modules[name] = None  # As if not installed.
    from robel_dm import suite
    try:
      robot = suite.RobotOptions('virtual')
      suite.load('dclaw', 'pose_fixed', seed=0, robot=robot)
    except ImportError as error:
      print(error)
    else:
      print('loaded')
  """)
  result = subprocess.run(
    [sys.executable, '-c', code],
    capture_output=True,
    text=True,
    timeout=300,
    cwd=_REPOSITORY,
    env={**os.environ, 'MUJOCO_GL': os.environ.get('MUJOCO_GL', 'egl')},
  )
  assert result.returncode == 0, result.stderr
  assert 'pip install -e ".[hardware]" (in the checkout)' in result.stdout, (
    result.stdout
  )
