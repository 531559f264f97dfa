"""The virtual servo chain through the unmodified `dynamixel_sdk`, over a
pseudo-terminal at 1,000,000 baud, as robel_dm's hardware client would:
round trips, group reads and writes, faults, and the server itself. The
SDK's packet deadline is raised for the tests that expect answers (a loaded
machine may deschedule the server thread for a while) and lowered to a few
milliseconds around the calls that are expected to time out. The codec and
a servo's registers on their own are in test_virtual_bus.py.
"""

import contextlib
import dataclasses
import os
import select
import signal
import subprocess
import sys
import threading
import time

import pytest

from robel_dm.commands import virtual_bus
from robel_dm.hardware import config, virtual
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Error, Instruction

sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
serial = pytest.importorskip('serial', reason='needs robel_dm[hardware]')


BAUD_RATE = 1_000_000


def _state_block(current: int, velocity: int, position: int) -> bytes:
  """A servo's (current, velocity, position) as a sync read returns them."""
  return (
    table.to_unsigned(current, 2).to_bytes(2, 'little')
    + table.to_unsigned(velocity, 4).to_bytes(4, 'little')
    + table.to_unsigned(position, 4).to_bytes(4, 'little')
  )


# --- Through the SDK ---------------------------------------------------------


class CountingPortHandler(sdk.PortHandler):
  """The SDK's port, counting the bytes it sends."""

  def __init__(self, port_name):
    super().__init__(port_name)
    self.bytes_written = 0

  def writePort(self, packet):  # noqa: N802 (SDK method name)
    written = super().writePort(packet)
    self.bytes_written += written
    return written


@dataclasses.dataclass
class Chain:
  bus: virtual.Bus
  server: virtual.PtyBusServer
  port: CountingPortHandler
  packets: 'sdk.Protocol2PacketHandler'

  def servo(self, motor_id: int) -> virtual.VirtualServo:
    return self.bus.servo(motor_id)

  def settle(self, timeout_s: float = 10.0) -> None:
    """Waits until the server has answered everything sent, then drops
    replies nobody read (late ones from a call that timed out, or replies
    to broadcasts not waited for)."""
    deadline = time.monotonic() + timeout_s
    while self.server.stats['bytes_in'] < self.port.bytes_written:
      assert time.monotonic() < deadline, 'the server fell behind'
      time.sleep(0.001)
    self.port.clearPort()


@contextlib.contextmanager
def _serve(ids, driver=None, faults=None):
  bus = virtual.Bus(virtual.make_servos(ids), driver, faults)
  with virtual.PtyBusServer(bus) as server:
    port = CountingPortHandler(server.device_path)
    assert port.openPort()
    assert port.setBaudRate(BAUD_RATE)
    try:
      yield Chain(bus, server, port, sdk.PacketHandler(2.0))
    finally:
      port.closePort()
  assert not server.errors


@pytest.fixture(autouse=True)
def tolerant_deadline(monkeypatch):
  """A ~0.5 s packet deadline for the bare SDK (which cannot tell a busy
  bus from a silent motor): at a load of 11 on 2 cores, ~100 ms timed out
  about once in 6 runs of the file."""
  monkeypatch.setattr(sdk.port_handler, 'LATENCY_TIMER', 250)


@contextlib.contextmanager
def short_deadline(chain: Chain):
  """A ~4 ms packet deadline, for calls that are expected to time out.

  Afterwards waits for the server and drops late replies, so that the next
  call cannot take one of them for its own answer.
  """
  saved = sdk.port_handler.LATENCY_TIMER
  sdk.port_handler.LATENCY_TIMER = 1
  try:
    yield
  finally:
    sdk.port_handler.LATENCY_TIMER = saved
    chain.settle()


@pytest.fixture
def open_chain():
  with contextlib.ExitStack() as stack:

    def open_(ids=(1, 2, 3), **kwargs) -> Chain:
      return stack.enter_context(_serve(ids, **kwargs))

    yield open_


@pytest.fixture
def chain(open_chain) -> Chain:
  return open_chain()


def _sync_read(chain: Chain, ids, address=126, length=10):
  reader = sdk.GroupSyncRead(chain.port, chain.packets, address, length)
  for motor_id in ids:
    assert reader.addParam(motor_id)
  return reader, reader.txRxPacket()


def _torque_on(chain: Chain, ids):
  for motor_id in ids:
    result, error = chain.packets.write1ByteTxRx(chain.port, motor_id, 64, 1)
    assert (result, error) == (sdk.COMM_SUCCESS, 0)


def test_ping_returns_model_number(chain):
  assert chain.packets.ping(chain.port, 2) == (1040, sdk.COMM_SUCCESS, 0)
  assert chain.servo(2).counters[Instruction.PING] == 1


@pytest.mark.slow
def test_broadcast_ping_finds_every_servo(open_chain):
  chain = open_chain([3, 1, 12])
  found, result = chain.packets.broadcastPing(chain.port)
  assert result == sdk.COMM_SUCCESS
  assert found == {1: [1040, 46], 3: [1040, 46], 12: [1040, 46]}


def test_read_write_round_trip(chain):
  packets, port = chain.packets, chain.port
  assert packets.write1ByteTxRx(port, 1, 65, 1) == (sdk.COMM_SUCCESS, 0)
  assert packets.read1ByteTxRx(port, 1, 65) == (1, sdk.COMM_SUCCESS, 0)
  assert packets.write2ByteTxRx(port, 2, 84, 1234) == (sdk.COMM_SUCCESS, 0)
  assert packets.read2ByteTxRx(port, 2, 84) == (1234, sdk.COMM_SUCCESS, 0)
  assert packets.write4ByteTxRx(port, 3, 112, 30_000) == (0, 0)
  assert packets.read4ByteTxRx(port, 3, 112) == (30_000, sdk.COMM_SUCCESS, 0)
  assert chain.servo(3).get(table.PROFILE_VELOCITY) == 30_000
  assert chain.servo(1).counters[Instruction.WRITE] == 1


def test_signed_values_survive_byte_stuffing(chain):
  servo = chain.servo(2)
  servo.set_present(-1234, -3, -1)
  read = protocol.encode_instruction(2, Instruction.READ, b'\x7e\0\x0a\0')
  wire = chain.bus.handle(protocol.parse(read)[0])
  assert b'\xff\xff\xfd\xfd' in wire  # The status packet is stuffed.
  data, result, error = chain.packets.readTxRx(chain.port, 2, 126, 10)
  assert (result, error) == (sdk.COMM_SUCCESS, 0)
  assert bytes(data) == _state_block(-1, -3, -1234)
  reader, result = _sync_read(chain, [1, 2, 3])
  assert result == sdk.COMM_SUCCESS
  assert table.to_signed(reader.getData(2, 126, 2), 2) == -1
  assert table.to_signed(reader.getData(2, 128, 4), 4) == -3
  assert table.to_signed(reader.getData(2, 132, 4), 4) == -1234
  assert reader.getData(1, 132, 4) == 2048


@pytest.mark.parametrize('robot', ['dclaw', 'dkitty'])
def test_sync_write_then_sync_read(open_chain, robot):
  ids = config.default(robot).joint_ids
  chain = open_chain(ids)
  torque = sdk.GroupSyncWrite(chain.port, chain.packets, 64, 1)
  goals = sdk.GroupSyncWrite(chain.port, chain.packets, 116, 4)
  expected = {}
  for n, motor_id in enumerate(ids):
    expected[motor_id] = 1000 + 100 * n
    assert torque.addParam(motor_id, [1])
    assert goals.addParam(motor_id, expected[motor_id].to_bytes(4, 'little'))
  assert torque.txPacket() == sdk.COMM_SUCCESS
  assert goals.txPacket() == sdk.COMM_SUCCESS
  reader, result = _sync_read(chain, ids)
  assert result == sdk.COMM_SUCCESS
  for motor_id in ids:
    assert reader.isAvailable(motor_id, 126, 10)
    assert reader.getData(motor_id, 132, 4) == expected[motor_id]
    assert reader.getData(motor_id, 128, 4) == 0
    assert reader.getData(motor_id, 126, 2) == 0
    assert chain.servo(motor_id).counters[Instruction.SYNC_WRITE] == 2
    assert chain.servo(motor_id).counters[Instruction.SYNC_READ] == 1
  assert chain.bus.goal_positions() == expected


def test_bulk_read_and_bulk_write(chain):
  _torque_on(chain, [1, 2, 3])
  writer = sdk.GroupBulkWrite(chain.port, chain.packets)
  assert writer.addParam(1, 116, 4, list((100).to_bytes(4, 'little')))
  assert writer.addParam(2, 65, 1, [1])
  assert writer.txPacket() == sdk.COMM_SUCCESS
  reader = sdk.GroupBulkRead(chain.port, chain.packets)
  assert reader.addParam(1, 132, 4)
  assert reader.addParam(2, 65, 1)
  assert reader.addParam(3, 144, 3)  # Voltage and temperature.
  assert reader.txRxPacket() == sdk.COMM_SUCCESS
  assert reader.getData(1, 132, 4) == 100
  assert reader.getData(2, 65, 1) == 1
  assert reader.getData(3, 144, 2) == 240
  assert reader.getData(3, 146, 1) == 35


def test_fast_sync_read(chain):
  _torque_on(chain, [1, 2, 3])
  chain.packets.write4ByteTxRx(chain.port, 3, 116, 4000)
  chain.servo(1).set_present(10, -3, -1)  # Unstuffed in fast replies.
  reader = sdk.GroupSyncRead(chain.port, chain.packets, 126, 10)
  for motor_id in (1, 2, 3):
    reader.addParam(motor_id)
  assert reader.fastSyncRead() == sdk.COMM_SUCCESS
  assert reader.getData(3, 132, 4) == 4000
  assert table.to_signed(reader.getData(1, 128, 4), 4) == -3


def test_reg_write_and_broadcast_action(chain):
  for motor_id in (1, 2):
    result = chain.packets.regWriteTxRx(chain.port, motor_id, 65, 1, [1])
    assert result == (sdk.COMM_SUCCESS, 0)
  assert chain.servo(1).get(table.LED) == 0
  assert chain.packets.action(chain.port, protocol.BROADCAST_ID) == 0
  assert chain.packets.read1ByteTxRx(chain.port, 1, 65)[0] == 1
  assert chain.packets.read1ByteTxRx(chain.port, 2, 65)[0] == 1
  assert chain.packets.read1ByteTxRx(chain.port, 3, 65)[0] == 0


def test_write_errors(chain):
  packets, port = chain.packets, chain.port
  _torque_on(chain, [1])
  assert packets.write1ByteTxRx(port, 1, 11, 4) == (0, Error.ACCESS)
  assert packets.write2ByteTxRx(port, 1, 0, 7) == (0, Error.ACCESS)
  assert packets.write4ByteTxRx(port, 1, 116, 5000) == (0, Error.DATA_LIMIT)
  assert packets.write2ByteTxRx(port, 1, 116, 5) == (0, Error.DATA_LENGTH)
  assert packets.write1ByteTxRx(port, 1, 68, 7) == (0, Error.DATA_RANGE)
  assert chain.servo(1).goal_position == 2048


def test_status_return_level(chain):
  packets, port = chain.packets, chain.port
  assert packets.write1ByteTxRx(port, 1, 68, 1) == (0, 0)
  with short_deadline(chain):
    result, _ = packets.write1ByteTxRx(port, 1, 65, 1)
  assert result == sdk.COMM_RX_TIMEOUT
  assert packets.write1ByteTxOnly(port, 1, 65, 0) == sdk.COMM_SUCCESS
  assert packets.read1ByteTxRx(port, 1, 65) == (0, sdk.COMM_SUCCESS, 0)
  packets.write1ByteTxOnly(port, 1, 68, 0)
  with short_deadline(chain):
    assert packets.read1ByteTxRx(port, 1, 65)[1] == sdk.COMM_RX_TIMEOUT
  assert packets.ping(port, 1) == (1040, sdk.COMM_SUCCESS, 0)


def test_baud_rate_change(chain):
  packets, port = chain.packets, chain.port
  assert packets.write1ByteTxRx(port, 1, 8, 1) == (0, 0)  # 57,600.
  with short_deadline(chain):
    assert packets.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
  assert port.setBaudRate(57_600)
  assert packets.ping(port, 1) == (1040, sdk.COMM_SUCCESS, 0)
  with short_deadline(chain):
    assert packets.ping(port, 2)[1] == sdk.COMM_RX_TIMEOUT


def test_driver_hooks():
  calls = []

  class Recorder(virtual.IdealDriver):
    def on_write(self, servos, ids):
      calls.append(('write', list(ids)))
      super().on_write(servos, ids)

    def on_read(self, servos, ids):
      calls.append(('read', list(ids)))

  with _serve([1, 2, 3], driver=Recorder()) as chain:
    chain.packets.write1ByteTxRx(chain.port, 2, 64, 1)
    chain.packets.write1ByteTxRx(chain.port, 2, 11, 1)  # Refused: no call.
    _sync_read(chain, [3, 1])
    chain.packets.read4ByteTxRx(chain.port, 2, 132)
    chain.packets.reboot(chain.port, 1)
  assert calls == [
    ('write', [2]),
    ('read', [3, 1]),
    ('read', [2]),
    ('write', [1]),
  ]


# --- Faults ------------------------------------------------------------------


def test_missing_motor(chain):
  chain.bus.faults.set_absent(2)
  with short_deadline(chain):
    assert chain.packets.ping(chain.port, 2)[1] == sdk.COMM_RX_TIMEOUT
    reader, result = _sync_read(chain, [1, 2, 3])
  assert result == sdk.COMM_RX_TIMEOUT
  assert not any(reader.isAvailable(i, 126, 10) for i in (1, 2, 3))
  writer = sdk.GroupSyncWrite(chain.port, chain.packets, 65, 1)
  for motor_id in (1, 2, 3):
    writer.addParam(motor_id, [1])
  assert writer.txPacket() == sdk.COMM_SUCCESS  # The loss is invisible.
  chain.settle()
  assert chain.servo(2).get(table.LED) == 0
  assert chain.servo(3).get(table.LED) == 1
  chain.bus.faults.set_absent(2, False)
  assert _sync_read(chain, [1, 2, 3])[1] == sdk.COMM_SUCCESS


def test_missing_motor_without_chain_break(open_chain):
  faults = virtual.Faults(absent={2}, chain_break=False)
  chain = open_chain(faults=faults)
  with short_deadline(chain):
    reader, result = _sync_read(chain, [1, 2, 3])
  assert result == sdk.COMM_RX_TIMEOUT  # The SDK discards servo 3's reply.
  assert chain.servo(3).counters[Instruction.SYNC_READ] == 1


def test_crc_corruption_then_recovery(chain):
  chain.bus.faults.corrupt_next(2)
  assert chain.packets.ping(chain.port, 2)[1] == sdk.COMM_RX_CORRUPT
  assert chain.packets.ping(chain.port, 2) == (1040, sdk.COMM_SUCCESS, 0)
  chain.bus.faults.corrupt_next(3)
  assert _sync_read(chain, [1, 2, 3])[1] == sdk.COMM_RX_CORRUPT
  reader, result = _sync_read(chain, [1, 2, 3])
  assert result == sdk.COMM_SUCCESS and reader.getData(3, 132, 4) == 2048


def test_instruction_with_bad_crc_is_answered_with_crc_error(chain):
  packet = bytearray(protocol.encode_instruction(1, Instruction.PING))
  packet[-1] ^= 0x55
  with serial.Serial(chain.server.device_path, BAUD_RATE, timeout=2) as raw:
    raw.write(bytes(packet))
    reply = raw.read(11)
  (status,) = protocol.parse(reply)
  assert status.id == 1 and status.error == Error.CRC
  assert chain.servo(1).crc_errors == 1
  assert chain.bus.stats['crc_errors'] == 1


def test_mute_then_recovery(chain):
  chain.bus.faults.mute_next(2)
  with short_deadline(chain):
    assert chain.packets.read4ByteTxRx(chain.port, 2, 132)[1] == (
      sdk.COMM_RX_TIMEOUT
    )
  assert chain.packets.read4ByteTxRx(chain.port, 2, 132) == (2048, 0, 0)
  chain.bus.faults.mute_next(1)
  with short_deadline(chain):
    assert _sync_read(chain, [1, 2, 3])[1] == sdk.COMM_RX_TIMEOUT
  assert _sync_read(chain, [1, 2, 3])[1] == sdk.COMM_SUCCESS
  assert not chain.bus.faults.mute


def test_hardware_error_without_shutdown(chain):
  _torque_on(chain, [2])
  chain.servo(2).inject_hardware_error(0x01)  # Input voltage: no shutdown.
  packets, port = chain.packets, chain.port
  value, result, error = packets.read4ByteTxRx(port, 2, 132)
  assert (value, result, error) == (2048, sdk.COMM_SUCCESS, 0x80)
  assert packets.read1ByteTxRx(port, 2, 70) == (0x01, 0, 0x80)
  assert packets.read1ByteTxRx(port, 2, 64) == (1, 0, 0x80)
  reader, result = _sync_read(chain, [1, 2, 3])
  assert result == sdk.COMM_SUCCESS  # Group reads drop the alert bit.
  assert reader.getData(2, 132, 4) == 2048
  assert packets.ping(port, 1) == (1040, 0, 0)


def test_overload_shutdown_and_reboot(chain):
  packets, port = chain.packets, chain.port
  _torque_on(chain, [1, 2, 3])
  chain.servo(2).inject_hardware_error(0x20)
  assert packets.read1ByteTxRx(port, 2, 70) == (0x20, 0, 0x80)
  assert packets.read1ByteTxRx(port, 2, 64) == (0, 0, 0x80)
  assert packets.write1ByteTxRx(port, 2, 64, 1) == (sdk.COMM_SUCCESS, 0x80)
  assert packets.read1ByteTxRx(port, 2, 64) == (0, 0, 0x80)
  assert _sync_read(chain, [1, 2, 3])[1] == sdk.COMM_SUCCESS
  assert packets.reboot(port, 2) == (sdk.COMM_SUCCESS, 0x80)
  assert packets.read1ByteTxRx(port, 2, 70) == (0, 0, 0)
  assert packets.write1ByteTxRx(port, 2, 64, 1) == (0, 0)
  assert packets.read1ByteTxRx(port, 2, 64) == (1, 0, 0)


def test_faults_can_change_while_serving(chain):
  stop = threading.Event()

  def toggle():
    while not stop.is_set():
      chain.bus.faults.corrupt_next(1)
      time.sleep(0.001)
      chain.bus.faults.clear()

  thread = threading.Thread(target=toggle)
  thread.start()
  try:
    results = {chain.packets.ping(chain.port, 1)[1] for _ in range(50)}
  finally:
    stop.set()
    thread.join()
  assert results <= {sdk.COMM_SUCCESS, sdk.COMM_RX_CORRUPT}


# --- Server ------------------------------------------------------------------


def test_garbage_and_fragments_on_the_wire(chain):
  ping = protocol.encode_instruction(3, Instruction.PING)
  with serial.Serial(chain.server.device_path, BAUD_RATE, timeout=2) as raw:
    for start in range(0, len(ping), 3):
      raw.write(b'\x00\xff' if start == 0 else b'')
      raw.write(ping[start : start + 3])
      raw.flush()
    reply = raw.read(14)
  (status,) = protocol.parse(reply)
  assert status.id == 3 and status.data == bytes([0x10, 0x04, 46])


def test_false_header_is_abandoned(chain):
  ping = protocol.encode_instruction(1, Instruction.PING)
  with serial.Serial(chain.server.device_path, BAUD_RATE, timeout=2) as raw:
    raw.write(b'\xff\xff\xfd\x00\x01\xff\x00' + ping)
    reply = raw.read(14)
  assert protocol.parse(reply)[0].id == 1
  assert chain.server.stats['resyncs'] >= 1


@pytest.mark.slow
def test_server_is_idle_without_traffic_and_stops_cleanly():
  bus = virtual.Bus(virtual.make_servos([1]))
  server = virtual.PtyBusServer(bus).start()
  path = server.device_path
  for _ in range(3):  # Reopen (EIO territory without the server's slave fd).
    port = sdk.PortHandler(path)
    assert port.openPort()
    assert sdk.PacketHandler(2.0).ping(port, 1)[1] == sdk.COMM_SUCCESS
    port.closePort()
  cpu = time.process_time()
  time.sleep(0.3)
  assert time.process_time() - cpu < 0.1
  server.stop()
  assert not server.running
  assert not os.path.exists(path)
  server.stop()  # Idempotent.
  with pytest.raises(RuntimeError):
    server.start()
  assert not server.errors


@pytest.mark.slow
def test_command_line_serves_a_robot():
  process = subprocess.Popen(
    [sys.executable, '-m', 'robel_dm.commands.virtual_bus', '--robot=dclaw'],
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    text=True,
  )
  try:
    ready, _, _ = select.select([process.stdout], [], [], 30)
    assert ready, 'the command printed no device path'
    path = process.stdout.readline().strip()
    port = sdk.PortHandler(path)
    assert port.openPort()
    packets = sdk.PacketHandler(2.0)
    for motor_id in (10, 32, 50, 60):
      assert packets.ping(port, motor_id) == (1040, sdk.COMM_SUCCESS, 0)
    port.closePort()
  finally:
    process.send_signal(signal.SIGTERM)
    try:
      returncode = process.wait(10)
    except subprocess.TimeoutExpired:
      process.kill()
      raise
  assert returncode == 0, process.stderr.read()


@pytest.mark.slow
def test_a_real_time_bus_answers_promptly_after_an_idle_spell(monkeypatch):
  """A read after minutes of silence simulates at most a second of them
  (the robot has settled), so the reply is not held past the deadline."""
  import math  # noqa: PLC0415

  from robel_dm import suite  # noqa: PLC0415
  from robel_dm.hardware.virtual import sim_robot  # noqa: PLC0415

  scene = suite.load('dclaw', 'turn_fixed', seed=0, time_limit=math.inf)
  clock = [100.0]
  monkeypatch.setattr(sim_robot.time, 'monotonic', lambda: clock[0])
  robot = sim_robot.SimulatedRobot(
    scene, config.default('dclaw'), realtime=True
  )
  bus = virtual_bus.build_bus(config.default('dclaw'))
  servos = {servo.motor_id: servo for servo in bus.servos}
  clock[0] += 600.0  # Ten idle minutes.
  robot.on_read(servos, [10])
  assert robot.physics.data.time == pytest.approx(1.0)
  clock[0] += 0.05  # A control period later: real time again.
  robot.on_read(servos, [10])
  assert robot.physics.data.time == pytest.approx(1.05)
