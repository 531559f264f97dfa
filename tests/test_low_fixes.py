"""Issue 39, item 5: the low ones.

A policy archive whose headers declare gigabytes is refused from the headers
(under a memory cap, in a child process); `evaluate` refuses a --output that
is a file the run reads; three bus failures are named by their real cause
(a wrong-length state reply, a wrong-length ping reply, a whole bus late);
a closed robot environment's physics says it is closed.
"""

import io
import subprocess
import sys
import textwrap
import zipfile

from absl import flags
import numpy as np
import pytest
import test_bad_input as bad_input

from robel_dm import policies, suite
from robel_dm.evaluation import cli
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Instruction

# The bus tests need the hardware extra (the virtual bus and
# test_robot_safety's fixtures); without it they skip, the others run.
try:
  import dynamixel_sdk  # noqa: F401
except ImportError:
  safety = None
else:
  import test_robot_safety as safety
needs_hardware = pytest.mark.skipif(
  safety is None, reason='needs robel_dm[hardware]'
)

FLAGS = flags.FLAGS

# --- A policy archive that declares gigabytes ---------------------------------

# 3 GiB of float64, declared by the header of a member that holds no data.
_HUGE_SHAPE = (3 * 2**30 // 8 // 1024, 1024)

_LOAD_UNDER_A_MEMORY_CAP = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (2**30, 2**30))  # 1 GiB.
from robel_dm import policies
try:
  policies.load(sys.argv[1])
except policies.PolicyError as error:
  print(error)
"""


def _huge_policy(path):
  """A sound policy, but for weight_0: its header declares 3 GiB."""
  bad_input._policy().save(path)  # noqa: SLF001
  with np.load(path) as data:
    arrays = {name: data[name] for name in data.files}
  header = io.BytesIO()
  np.lib.format.write_array_header_1_0(
    header, {'descr': '<f8', 'fortran_order': False, 'shape': _HUGE_SHAPE}
  )
  with zipfile.ZipFile(path, 'w') as archive:
    for name, array in arrays.items():
      member = io.BytesIO()
      if name == 'weight_0':
        member.write(header.getvalue())
      else:
        np.lib.format.write_array(member, array)
      archive.writestr(f'{name}.npy', member.getvalue())
  return path


@pytest.mark.slow
def test_a_policy_declaring_gigabytes_is_refused_from_its_headers(tmp_path):
  path = _huge_policy(tmp_path / 'policy.npz')
  child = subprocess.run(
    [sys.executable, '-c', textwrap.dedent(_LOAD_UNDER_A_MEMORY_CAP), path],
    capture_output=True,
    text=True,
    timeout=120,
  )
  # One line naming the file, the array and its size; no MemoryError.
  assert child.returncode == 0, child.stderr
  assert not child.stderr
  (line,) = child.stdout.splitlines()
  assert str(path) in line
  assert 'array weight_0 declares 3,072.0 MiB' in line
  assert 'float64, shape (393216, 1024)' in line


# --- evaluate --output naming a file the run reads ----------------------------


@pytest.fixture
def run_main(evaluate_flags, capsys):
  """The command's main() with command-line flags: (exit code, stdout,
  stderr)."""

  def run(*argv):
    FLAGS.unparse_flags()
    FLAGS(['evaluate', *argv])
    code = cli.main(['evaluate'])
    out, err = capsys.readouterr()
    return code, out, err

  yield run
  FLAGS.unparse_flags()


def _same_path(path):
  return path


def _through_a_linked_folder(path):
  link = path.parent.parent / 'linked'
  link.symlink_to(path.parent)
  return link / path.name


@pytest.mark.parametrize('spell', [_same_path, _through_a_linked_folder])
def test_an_output_that_is_the_policy_file_is_refused(
  spell, run_main, built, tmp_path
):
  folder = tmp_path / 'run'
  folder.mkdir()
  policy = bad_input._write(bad_input._policy(), folder / 'p.npz')  # noqa: SLF001
  before = policy.read_bytes()
  output = spell(policy)
  code, out, err = run_main(
    f'--policy={policy}', '--domain=dclaw', '--task=pose_fixed',
    '--episodes=1', f'--output={output}',
  )  # fmt: skip
  bad_input._assert_one_line_error(code, out, err, output, '--policy')  # noqa: SLF001
  assert not built
  assert policy.read_bytes() == before


def test_an_output_that_is_the_baseline_policy_is_refused(
  run_main, built, tmp_path, monkeypatch
):
  # A copy of the shipped baselines: a run that wrongly went ahead would
  # replace the copy, not the repository's file.
  shipped = policies.baseline_path('dclaw', 'pose_fixed')
  (tmp_path / shipped.name).write_bytes(shipped.read_bytes())
  monkeypatch.setattr(policies.assets, 'baselines_dir', lambda: tmp_path)
  output = tmp_path / shipped.name
  code, out, err = run_main(
    '--policy=baseline', '--domain=dclaw', '--task=pose_fixed',
    '--episodes=1', f'--output={output}',
  )  # fmt: skip
  bad_input._assert_one_line_error(code, out, err, output, '--policy')  # noqa: SLF001
  assert not built
  assert output.read_bytes() == shipped.read_bytes()


# --- Bus failures named by their cause ----------------------------------------

if safety is not None:
  lockstep = safety.lockstep
  claw = safety.claw
  short_timeouts = safety.short_timeouts


def _device_path(env) -> str:
  return env.robot.client._device_path  # noqa: SLF001


def _late_reply_ahead_of(monkeypatch, bus, matches, late_reply, times):
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


def _state_read(packet) -> bool:
  address = table.STATE_BLOCK_ADDRESS.to_bytes(2, 'little')
  return packet.instruction == Instruction.SYNC_READ and (
    packet.params[:2] == address
  )


def _ping_of(motor_id):
  return lambda packet: (
    packet.instruction == Instruction.PING and packet.id == motor_id
  )


@pytest.mark.slow
@needs_hardware
def test_wrong_length_state_replies_are_not_called_a_bad_checksum(
  lockstep, claw, monkeypatch
):
  # A ping to motor 10 that timed out was answered late, ahead of every
  # attempt of the state read: 3 bytes where the read expects its block.
  late_ping_reply = protocol.encode_status(10, 0, bytes([0x10, 0x04, 46]))
  left = _late_reply_ahead_of(
    monkeypatch, claw.virtual_bus, _state_read, late_ping_reply, times=3
  )
  with pytest.raises(dynamixel.DynamixelError) as error:
    claw.step(np.zeros(9))
  assert left == [0]
  message = str(error.value)
  assert error.value.motor_ids == (10,)
  assert (
    f'motor 10 answered the state read on {_device_path(claw)} with 3 bytes '
    f'instead of {table.STATE_BLOCK_SIZE}, 3 times in a row'
  ) in message
  assert 'checksum' not in message and 'corrupt' not in message


@pytest.mark.slow
@needs_hardware
def test_a_wrong_length_ping_reply_is_not_called_silence(claw, monkeypatch):
  # Motor 22 answers every ping with 5 bytes (model, firmware, 2 more).
  client, bus = claw.robot.client, claw.virtual_bus
  handle, pings = bus.handle, []

  def five_byte_pings_of_22(packet, baud_rate=None):
    reply = handle(packet, baud_rate)
    if _ping_of(22)(packet):
      pings.append(reply)
      return protocol.encode_status(22, 0, bytes([0x10, 0x04, 46, 0, 0]))
    return reply

  monkeypatch.setattr(bus, 'handle', five_byte_pings_of_22)
  with pytest.raises(dynamixel.MissingMotorError) as error:
    client.ping(22)
  assert len(pings) == 3  # 1 + 2 retries, each answered.
  path = _device_path(claw)
  assert str(error.value) == (
    f'motor 22 answered a ping with 5 bytes instead of 3 (a late reply to '
    f'an earlier packet?) on {path}'
  )
  # The same when connecting: the pings that check the motors.
  client.disconnect()
  with pytest.raises(dynamixel.MissingMotorError) as error:
    client.connect()
  assert error.value.motor_ids == (22,)
  assert 'motor 22 answered a ping with 5 bytes instead of 3' in str(
    error.value
  )
  assert 'do not answer' not in str(error.value)


def _stall(monkeypatch, bus, reads: int):
  """The whole bus late: its replies to the next `reads` state reads come
  only ahead of its reply to the next ping of motor 10."""
  handle, held = bus.handle, []

  def late_bus(packet, baud_rate=None):
    reply = handle(packet, baud_rate)
    if len(held) < reads and _state_read(packet):
      held.append(reply)
      return b''
    if held and held[0] is not None and _ping_of(10)(packet):
      reply = b''.join(held) + reply
      held[:] = [None] * reads  # Sent.
    return reply

  monkeypatch.setattr(bus, 'handle', late_bus)
  return held


@pytest.mark.slow
@needs_hardware
def test_a_whole_bus_stall_is_not_blamed_on_the_first_motor(
  lockstep, short_timeouts, claw, monkeypatch
):
  env, bus = claw, claw.virtual_bus
  ids = tuple(env.robot.client.motor_ids)
  # Motor 10 dead: still named (the chain after it is silent too).
  bus.faults.set_absent(10)
  with pytest.raises(dynamixel.MissingMotorError) as error:
    env.step(np.zeros(9))
  assert f'motors [10] stopped answering on {_device_path(env)}' in str(
    error.value
  )
  bus.faults.set_absent(10, False)
  env.reset()
  # The whole bus late for the 3 attempts of a state read: its replies come
  # with the first diagnostic ping's, which they spoil; all answer then.
  held = _stall(monkeypatch, bus, reads=3)
  with pytest.raises(dynamixel.DynamixelError) as error:
    env.step(np.zeros(9))
  assert held == [None] * 3  # All held, then sent late.
  message = str(error.value)
  assert not isinstance(error.value, dynamixel.MissingMotorError)
  assert error.value.motor_ids == ids
  assert (
    f'no motor answered the state read on {_device_path(env)}, 3 times in '
    'a row, yet every motor answered a ping right after: the whole bus '
    'stalled'
  ) in message
  assert 'motor 10' not in message and '[10]' not in message


# --- A closed robot environment's physics -------------------------------------


@pytest.mark.slow
@needs_hardware
def test_a_closed_robot_physics_says_it_is_closed():
  env = suite.load(
    'dclaw', 'pose_fixed', seed=0, robot=suite.RobotOptions('virtual')
  )
  env.reset()
  physics = env.physics
  env.close()
  for use in (
    lambda: physics.render(64, 64),
    physics.forward,
    physics.step,
    lambda: physics.data.qpos,
  ):
    # A RuntimeError as the closed environment's; a ReferenceError as
    # dm_control's freed physics.
    with pytest.raises(RuntimeError, match='environment is closed') as error:
      use()
    assert isinstance(error.value, ReferenceError)
