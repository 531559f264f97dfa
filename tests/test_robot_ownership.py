"""A robot belongs to the process that opened it (issue 39, items 1 and 4).

A forked child (os.fork, multiprocessing's fork start method) inherits the
robot, the exit handlers and the signal handlers: it must neither drive nor
release its parent's robot, however it ends. A robot released by anyone
else (another program on the bus, a motor that lost power) is noticed on
the next step, not driven on limp. The first Ctrl-C releases a robot that a
non-daemon worker thread drives. The cases that end processes run child
Pythons against a standalone virtual bus (test_robot_safety's helpers) and
read Torque Enable back through the SDK; the others run in-process.
"""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import child_signals
import numpy as np
import pytest

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Instruction

# Without the hardware extra these tests are skipped, not errors.
sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
# Its fixtures and helpers need the extra too.
import test_robot_safety as safety  # noqa: E402

claw = safety.claw
standalone_bus = safety.standalone_bus
_torque = safety.read_torque
_wait_for_line = safety._wait_for_line  # noqa: SLF001
_STARTUP_TIMEOUT_S = safety._STARTUP_TIMEOUT_S  # noqa: SLF001

_CLAW_IDS = [m.id for m in config_lib.default('dclaw').joints]


def _child(device_path: str, body: str, stdin=None) -> subprocess.Popen:
  """Runs `body` in a child Python as test_robot_safety's `_child` does
  (DEVICE set, a reply deadline of about 1 s); stdin may be a pipe. It
  leads a session (and process group) of its own, which `_finish` can
  end whole."""
  code = (
    'import json, numpy as np\n'
    'import dynamixel_sdk\n'
    'from robel_dm import suite\n'
    'dynamixel_sdk.port_handler.LATENCY_TIMER = 500\n'
    f'DEVICE = {device_path!r}\n' + textwrap.dedent(body)
  )
  return subprocess.Popen(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-c', code],
    stdin=stdin,
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
    start_new_session=True,
  )


def _finish(child, timeout_s: float = 60.0) -> tuple[str, str]:
  """The child's (stdout, stderr) once it ended. If it hangs, it and the
  processes it forked (which hold its pipes) are killed, and the test
  fails."""
  try:
    return child.communicate(timeout=timeout_s)
  except subprocess.TimeoutExpired:
    os.killpg(child.pid, signal.SIGKILL)
    _, errors = child.communicate()
    pytest.fail(f'the child hung for {timeout_s} s: {errors}')
  finally:
    if child.poll() is None:  # E.g. the test failed while it ran.
      os.killpg(child.pid, signal.SIGKILL)
      child.communicate()


def _last_json(output: str):
  lines = [line for line in output.splitlines() if line.startswith('{')]
  assert lines, output
  return json.loads(lines[-1])


# --- A forked child -----------------------------------------------------------

# The parent opens the robot and steps; a child forks off and ends in one of
# the ways the issue names; the parent then reads its own motors' torque
# and steps on. Ends normally: its exit handler releases the robot.
_PARENT = """
import multiprocessing, os, sys, time
from robel_dm.hardware.dynamixel import control_table as table

def wait(ready):
  ready.set()
  time.sleep(60)

def remember(queue):  # A Pool worker's initializer.
  STARTED.append(queue)

def busy(_):  # A Pool task that reports its worker, then works on.
  STARTED[0].put(os.getpid())
  time.sleep(60)

STARTED = []

robot = suite.RobotOptions(DEVICE, reset='move')
env = suite.load('dclaw', 'pose_fixed', robot=robot)
env.reset()
for _ in range(3):
  env.step(np.zeros(9))
ids = env.robot.joint_ids
fork = multiprocessing.get_context('fork')
child = {{}}
{scenario}
held = env.robot.client.read_register(table.TORQUE_ENABLE, ids)
steps = 0
for _ in range(10):
  env.step(np.zeros(9))
  steps += 1
print(json.dumps({{'child': child, 'torqued': sorted(
    i for i, on in held.items() if on), 'steps': steps}}), flush=True)
"""

_SCENARIOS = {
  # The child tries to drive the robot, closes its copy of the environment
  # and ends through sys.exit (atexit and finalizers run in it).
  'os.fork-sys.exit': """
read_end, write_end = os.pipe()
pid = os.fork()
if pid == 0:
  os.close(read_end)
  outcomes = []
  for attempt in (lambda: env.step(np.zeros(9)), env.reset):
    try:
      attempt()
      outcomes.append('drove the robot')
    except Exception as error:
      outcomes.append(f'{type(error).__name__}: {error}')
  env.close()
  os.write(write_end, json.dumps(outcomes).encode())
  sys.exit(0)
os.close(write_end)
with os.fdopen(read_end) as pipe:
  child['outcomes'] = json.loads(pipe.read())
child['status'] = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
""",
  # Process.terminate() sends SIGTERM to the child.
  'Process.terminate': """
ready = fork.Event()
process = fork.Process(target=wait, args=(ready,))
process.start()
assert ready.wait(30)
process.terminate()
process.join(30)
child['status'] = process.exitcode
""",
  # Pool.terminate() sends SIGTERM to every worker still working (an idle
  # one may take the pool's stop sentinel first): both are busy here.
  'Pool.terminate': """
started = fork.SimpleQueue()
pool = fork.Pool(2, initializer=remember, initargs=(started,))
pool.map_async(busy, range(2))
child['workers'] = len({started.get(), started.get()})
pool.terminate()
pool.join()
""",
}


@pytest.mark.slow
@pytest.mark.parametrize('scenario', list(_SCENARIOS))
def test_a_forked_child_leaves_its_parents_robot_alone(
  standalone_bus, scenario
):
  device_path, _ = standalone_bus
  child = _child(
    device_path, _PARENT.format(scenario=_SCENARIOS[scenario].strip())
  )
  output, errors = _finish(child, timeout_s=120)
  assert child.returncode == 0, errors
  report = _last_json(output)
  # The parent's motors kept their torque, and it stepped on.
  assert report['torqued'] == _CLAW_IDS, errors
  assert report['steps'] == 10
  if scenario == 'os.fork-sys.exit':
    # The child was refused, naming the process the robot belongs to.
    for outcome in report['child']['outcomes']:
      assert outcome.startswith('RobotOwnerError'), report
      assert f'belongs to process {child.pid}' in outcome, report
    assert report['child']['status'] == 0
  elif scenario == 'Process.terminate':
    # Killed by SIGTERM, as a child without a robot of its own is.
    assert report['child']['status'] == -signal.SIGTERM
  else:
    assert report['child']['workers'] == 2
  # Its owner released it on the way out.
  assert _torque(device_path) == dict.fromkeys(_CLAW_IDS, 0)


_FORK_IN_PROCESS = """
import json, os, signal, sys, time
import numpy as np
from robel_dm import suite
from robel_dm.hardware import shutdown
robot = suite.RobotOptions('virtual')
env = suite.load('dclaw', 'pose_fixed', seed=0, robot=robot)
env.reset()
bus = env.virtual_bus
env.step(np.zeros(9))
packets = bus.stats['packets']
read_end, write_end = os.pipe()
pid = os.fork()
if pid == 0:  # The child: tries everything, reports, dies of SIGTERM.
  try:
    os.close(read_end)
    outcomes = []
    for attempt in (lambda: env.step(np.zeros(9)), env.reset,
                    env.robot.release, env.close, shutdown.release_all):
      try:
        attempt()
        outcomes.append('ok')
      except Exception as error:
        outcomes.append(f'{type(error).__name__}: {error}')
    os.write(write_end, json.dumps(outcomes).encode())
    os.close(write_end)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(10)
  finally:
    os._exit(3)
os.close(write_end)
with os.fdopen(read_end) as pipe:
  outcomes = json.loads(pipe.read() or 'null')
_, status = os.waitpid(pid, 0)
sent = bus.stats['packets'] - packets
ids = (10, 11, 12, 20, 21, 22, 30, 31, 32)
held_after_child = all(bus.servo(i).torque_enabled for i in ids)
stepped = env.step(np.zeros(9)).mid()  # The parent drives on.
held = all(bus.servo(i).torque_enabled for i in ids)
env.close()
print(json.dumps({'owner': os.getpid(), 'outcomes': outcomes,
                  'signaled': os.WIFSIGNALED(status),
                  'signal': os.WTERMSIG(status) if os.WIFSIGNALED(status)
                  else None, 'sent': sent, 'held_after_child': held_after_child,
                  'stepped': bool(stepped), 'held': held}))
"""


@pytest.mark.slow
def test_a_forked_child_sends_nothing_to_its_parents_bus():
  # In-process: the child shares the parent's pty and bus thread, so
  # anything it sent would reach the parent's motors. In a fresh
  # interpreter: a fork of the test run (JAX's threads) can deadlock.
  result = subprocess.run(
    [sys.executable, '-c', _FORK_IN_PROCESS],
    capture_output=True,
    text=True,
    timeout=120,
    env={**os.environ, 'MUJOCO_GL': 'egl'},
    preexec_fn=child_signals.default,
  )
  assert result.returncode == 0, result.stderr[-2000:]
  report = json.loads(result.stdout.strip().splitlines()[-1])
  outcomes = report['outcomes']
  owner = f'belongs to process {report["owner"]}'
  assert [owner in outcome for outcome in outcomes] == [
    True,
    True,
    True,
    False,
    False,
  ], outcomes
  assert outcomes[3:] == ['ok', 'ok'], outcomes
  assert report['signaled'] and report['signal'] == signal.SIGTERM
  # Nothing reached the bus; the parent's robot is held and steps on.
  assert report['sent'] == 0
  assert report['held_after_child'] and report['stepped'] and report['held']


# --- Released by someone else -------------------------------------------------


@pytest.mark.slow
def test_a_robot_released_by_someone_else_stops_on_the_next_step(claw):
  env, bus = claw, claw.virtual_bus
  env.step(np.zeros(9))
  for motor_id in (10, 11):  # E.g. another program on the bus.
    bus.servo(motor_id).set(table.TORQUE_ENABLE, 0)
  with pytest.raises(dynamixel.RobotReleasedError) as error:
    env.step(np.zeros(9))
  assert error.value.motor_ids == (10, 11)
  assert 'motors [10, 11] lost their torque' in str(error.value)
  assert not any(s.torque_enabled for s in bus.servos)  # All released.
  with pytest.raises(dynamixel.RobotReleasedError, match='reset'):
    env.step(np.zeros(9))
  env.reset()  # Brings the robot back.
  assert env.step(np.zeros(9)).mid()
  assert all(bus.servo(i).torque_enabled for i in _CLAW_IDS)


def test_a_motor_that_cut_its_own_torque_is_named_with_its_error(claw):
  # A servo's overload shutdown also turns its torque off: the error says
  # why, not that someone released it.
  env, bus = claw, claw.virtual_bus
  env.step(np.zeros(9))
  bus.servo(21).inject_hardware_error(0x20)
  with pytest.raises(dynamixel.MotorFaultError, match='motor 21: overload'):
    env.step(np.zeros(9))
  assert not any(s.torque_enabled for s in bus.servos)


_STEP_ON_REQUEST = """
import sys
robot = suite.RobotOptions(DEVICE, reset='move')
env = suite.load('dclaw', 'pose_fixed', robot=robot)
env.reset()
print('ready', flush=True)
for _ in sys.stdin:  # One step per line.
  try:
    env.step(np.zeros(9))
    print('stepped', flush=True)
  except Exception as error:
    print(f'{type(error).__name__}: {error}', flush=True)
"""


def _broadcast_torque_off() -> bytes:
  """The packet another program sends to release every motor."""
  address = table.TORQUE_ENABLE.address.to_bytes(2, 'little')
  return protocol.encode_instruction(
    sdk.BROADCAST_ID, Instruction.WRITE, address + b'\0'
  )


@pytest.mark.slow
def test_a_robot_released_by_another_program_stops_the_next_step(
  standalone_bus,
):
  device_path, _ = standalone_bus
  child = _child(device_path, _STEP_ON_REQUEST, stdin=subprocess.PIPE)
  try:
    assert _wait_for_line(child.stdout, _STARTUP_TIMEOUT_S) == 'ready'

    def step() -> str:
      child.stdin.write('\n')
      child.stdin.flush()
      return _wait_for_line(child.stdout, _STARTUP_TIMEOUT_S)

    assert [step(), step()] == ['stepped', 'stepped']
    # While the child waits between steps, a program that ignores the
    # port's lock releases every motor (its packet needs no reply).
    port = os.open(device_path, os.O_WRONLY | os.O_NOCTTY)
    try:
      os.write(port, _broadcast_torque_off())
    finally:
      os.close(port)
    outcome = step()
    assert outcome.startswith('RobotReleasedError: motors '), outcome
    assert f'{_CLAW_IDS} lost their torque' in outcome, outcome
    assert 'released by another process or program' in outcome, outcome
    assert 'the robot was released after an error' in step()
  finally:
    _, errors = _finish(child)  # Closes its stdin: it ends.
  assert child.returncode == 0, errors
  assert _torque(device_path) == dict.fromkeys(_CLAW_IDS, 0)


# --- Ctrl-C while a worker thread drives the robot ----------------------------

# The main thread waits for a non-daemon worker that drives the robot.
_DRIVE_FROM_A_WORKER = """
import signal, threading, time

def drive():
  robot = suite.RobotOptions(DEVICE, reset='move')
  env = suite.load('dclaw', 'pose_fixed', robot=robot)
  env.reset()
  print('stepping', flush=True)
  while True:
    env.step(np.zeros(9))

worker = threading.Thread(target=drive, name='robot')
worker.start()
{main_thread}
"""


@pytest.mark.slow
@pytest.mark.parametrize(
  'main_thread',
  ['while worker.is_alive():\n  time.sleep(0.1)', 'signal.pause()'],
  ids=['polling', 'pausing'],
)
def test_the_first_ctrl_c_releases_a_robot_driven_from_a_worker_thread(
  standalone_bus, main_thread
):
  device_path, _ = standalone_bus
  child = _child(
    device_path, _DRIVE_FROM_A_WORKER.format(main_thread=main_thread)
  )
  try:
    assert _wait_for_line(child.stdout, _STARTUP_TIMEOUT_S) == 'stepping'
    time.sleep(0.3)  # Mid-episode.
    child.send_signal(signal.SIGINT)  # Once.
  finally:
    _, errors = _finish(child, timeout_s=30)
  # It ended within the timeout (it used to wait for a second Ctrl-C),
  # the robot released.
  assert _torque(device_path) == dict.fromkeys(_CLAW_IDS, 0), errors
  assert child.returncode == -signal.SIGINT, errors
  # Python waited for the worker: its next command was refused, naming the
  # interrupt.
  assert 'were released on SIGINT' in errors, errors
