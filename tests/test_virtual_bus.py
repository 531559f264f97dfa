"""Tests of the Protocol 2.0 codec and the virtual servo chain.

The chain is driven through the unmodified `dynamixel_sdk` over a
pseudo-terminal at 1,000,000 baud, as robel_dm's hardware client would. The
SDK's packet deadline is raised for the tests that expect answers (a loaded
machine may deschedule the server thread for a while) and lowered to a few
milliseconds around the calls that are expected to time out.
"""

import os
import random
import select
import signal
import subprocess
import sys

import pytest

from robel_dm.commands import virtual_bus
from robel_dm.hardware import config, virtual
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Error, Instruction

sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
serial = pytest.importorskip('serial', reason='needs robel_dm[hardware]')

BAUD_RATE = 1_000_000
# Examples from docs/dynamixel.md section 1.1 (taken from the e-manual).
EXAMPLE_PACKETS = {
  'ping': (
    protocol.encode_instruction(1, Instruction.PING),
    'FF FF FD 00 01 03 00 01 19 4E',
  ),
  'ping status': (
    protocol.encode_status(1, 0, bytes([0x06, 0x04, 0x26])),
    'FF FF FD 00 01 07 00 55 00 06 04 26 65 5D',
  ),
  'read': (
    protocol.encode_instruction(1, Instruction.READ, bytes([132, 0, 4, 0])),
    'FF FF FD 00 01 07 00 02 84 00 04 00 1D 15',
  ),
  'write': (
    protocol.encode_instruction(
      1, Instruction.WRITE, bytes([116, 0]) + (512).to_bytes(4, 'little')
    ),
    'FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89',
  ),
  'sync read': (
    protocol.encode_instruction(
      protocol.BROADCAST_ID, Instruction.SYNC_READ, bytes([132, 0, 4, 0, 1, 2])
    ),
    'FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA',
  ),
  'empty status': (
    protocol.encode_status(1, 0),
    'FF FF FD 00 01 04 00 55 00 A1 0C',
  ),
}


def _state_block(current: int, velocity: int, position: int) -> bytes:
  return (
    table.to_unsigned(current, 2).to_bytes(2, 'little')
    + table.to_unsigned(velocity, 4).to_bytes(4, 'little')
    + table.to_unsigned(position, 4).to_bytes(4, 'little')
  )


# --- Protocol ----------------------------------------------------------------


def test_crc_check_value():
  assert protocol.crc16(b'123456789') == 0xFEE8
  assert protocol.crc16(b'56789', protocol.crc16(b'1234')) == 0xFEE8


def test_crc_matches_sdk():
  handler = sdk.PacketHandler(2.0)
  rng = random.Random(0)
  for _ in range(200):
    data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
    assert protocol.crc16(data) == handler.updateCRC(0, list(data), len(data))


@pytest.mark.parametrize('name', sorted(EXAMPLE_PACKETS))
def test_example_packets(name):
  encoded, expected = EXAMPLE_PACKETS[name]
  assert encoded == bytes.fromhex(expected)
  (packet,) = protocol.parse(encoded)
  assert packet.crc_ok
  assert packet.id == encoded[4]
  assert packet.instruction == encoded[7]


def test_stuffing_of_negative_current_and_velocity():
  # docs/dynamixel.md section 1.2: current -1 (FF FF) then velocity -3
  # (FD FF FF FF).
  data = _state_block(current=-1, velocity=-3, position=2048)
  encoded = protocol.encode_status(1, 0, data)
  assert bytes.fromhex('55 00 FF FF FD FD FF FF FF') in encoded
  assert int.from_bytes(encoded[5:7], 'little') == 15  # 14 unstuffed.
  (packet,) = protocol.parse(encoded)
  assert packet.crc_ok and packet.error == 0 and packet.data == data


def test_stuffing_matches_sdk():
  handler = sdk.PacketHandler(2.0)
  rng = random.Random(1)
  alphabet = [0xFF, 0xFF, 0xFD, 0x00, 0x55]
  for _ in range(300):
    params = bytes(rng.choice(alphabet) for _ in range(rng.randrange(12)))
    length = len(params) + 3
    packet = [0xFF, 0xFF, 0xFD, 0, 7, length & 0xFF, length >> 8, 0x03]
    packet = handler.addStuffing(packet + list(params) + [0, 0])
    size = len(packet)
    crc = handler.updateCRC(0, packet, size - 2)
    packet[size - 2 :] = [crc & 0xFF, crc >> 8]
    assert protocol.encode_instruction(7, 0x03, params) == bytes(packet)
    assert protocol.unstuff(protocol.stuff(params)) == params


def test_parser_skips_garbage_and_reassembles_fragments():
  packets = [
    protocol.encode_instruction(3, Instruction.PING),
    protocol.encode_status(4, 0x80, _state_block(-1, -3, -5)),
    protocol.encode_instruction(254, Instruction.SYNC_READ, b'\x84\0\4\0\1\2'),
  ]
  stream = b'\x00\xff\x13' + packets[0] + b'\xff\xff' + packets[1] + packets[2]
  parser = protocol.PacketParser()
  parsed = []
  rng = random.Random(2)
  position = 0
  while position < len(stream):
    step = rng.randrange(1, 4)
    parsed += parser.feed(stream[position : position + step])
    position += step
  assert [(p.id, p.instruction) for p in parsed] == [
    (3, 1),
    (4, 0x55),
    (254, 0x82),
  ]
  assert parsed[1].error == 0x80
  assert parsed[1].data == _state_block(-1, -3, -5)
  assert all(p.crc_ok for p in parsed)
  assert parser.discarded == 5 and parser.pending == 0


def test_parser_reports_bad_crc_and_recovers():
  good = protocol.encode_instruction(1, Instruction.READ, b'\x84\0\4\0')
  bad = good[:-1] + bytes([good[-1] ^ 1])
  parsed = protocol.PacketParser().feed(bad + good)
  assert [p.crc_ok for p in parsed] == [False, True]
  assert parsed[0].id == 1 and parsed[0].instruction == Instruction.READ


def test_parser_resync_abandons_a_false_header():
  parser = protocol.PacketParser()
  ping = protocol.encode_instruction(1, Instruction.PING)
  assert parser.feed(b'\xff\xff\xfd\x00\x01\xff\x00' + ping) == []
  (packet,) = parser.resync()
  assert packet.instruction == Instruction.PING and packet.crc_ok


def test_fast_status_layout():
  blocks = [(0, 1, b'\x01\x02\x03\x04'), (0x80, 2, b'\xff\xff\xfd\x00')]
  encoded = protocol.encode_fast_status(blocks)
  assert encoded[4] == protocol.BROADCAST_ID
  assert int.from_bytes(encoded[5:7], 'little') == 1 + 2 * (4 + 4)
  assert b'\xfd\xfd' not in encoded  # Fast replies are never stuffed.
  first_block_end = 8 + 2 + 4
  first_crc = encoded[first_block_end : first_block_end + 2]
  assert int.from_bytes(first_crc, 'little') == protocol.crc16(
    encoded[:first_block_end]
  )
  assert protocol.crc16(encoded[:-2]) == int.from_bytes(encoded[-2:], 'little')


# --- VirtualServo ------------------------------------------------------------


def test_servo_defaults():
  servo = virtual.VirtualServo(7)
  assert servo.motor_id == 7 and servo.model_number == 1040
  assert servo.firmware == 46
  assert table.BAUD_RATES[servo.get(table.BAUD_RATE)] == 1_000_000
  assert servo.get(table.RETURN_DELAY_TIME) == 0
  assert servo.operating_mode == table.POSITION_MODE
  assert servo.get(table.SHUTDOWN) == 52
  assert servo.get(table.MIN_POSITION_LIMIT) == 0
  assert servo.get(table.MAX_POSITION_LIMIT) == 4095
  assert servo.status_return_level == 2
  assert servo.get(table.CURRENT_LIMIT) == 689
  assert servo.get(table.VELOCITY_LIMIT) == 285
  assert servo.get(table.PRESENT_TEMPERATURE) == 35
  assert not servo.torque_enabled
  assert servo.goal_position == servo.present_position == 2048
  assert len(servo.table) == 662
  w210 = virtual.VirtualServo(1, model_number=1030)
  assert w210.get(table.CURRENT_LIMIT) == 1193
  assert w210.get(table.PRESENT_INPUT_VOLTAGE) == 120


def test_servo_write_rules():
  servo = virtual.VirtualServo(1)
  goal = table.GOAL_POSITION.address

  def write(item, value):
    raw = table.to_unsigned(value, item.size).to_bytes(item.size, 'little')
    return servo.write(item.address, raw)

  assert write(table.OPERATING_MODE, 4) == Error.NONE
  assert write(table.OPERATING_MODE, 3) == Error.NONE
  assert write(table.TORQUE_ENABLE, 1) == Error.NONE
  assert write(table.OPERATING_MODE, 4) == Error.ACCESS  # EEPROM.
  assert write(table.MODEL_NUMBER, 1) == Error.ACCESS  # Read-only.
  assert write(table.PRESENT_POSITION, 1) == Error.ACCESS
  assert servo.write(66, b'\0') == Error.ACCESS  # Reserved.
  assert servo.write(goal, b'\0\0') == Error.DATA_LENGTH
  assert servo.write(goal + 1, b'\0\0\0\0') == Error.DATA_LENGTH
  assert write(table.STATUS_RETURN_LEVEL, 3) == Error.DATA_RANGE
  assert write(table.GOAL_POSITION, 4096) == Error.DATA_LIMIT
  assert write(table.GOAL_POSITION, -1) == Error.DATA_LIMIT
  assert write(table.GOAL_VELOCITY, -286) == Error.DATA_LIMIT
  assert write(table.GOAL_CURRENT, 690) == Error.DATA_LIMIT
  assert servo.goal_position == 2048  # Nothing stored on error.
  assert write(table.GOAL_POSITION, 4095) == Error.NONE
  assert servo.goal_position == 4095
  # Several items in one write: LED (65) after Torque Enable (64).
  assert servo.write(64, b'\x01\x01') == Error.NONE
  assert servo.get(table.LED) == 1
  assert servo.write(660, b'\0\0\0') == Error.ACCESS  # Past the table.


def test_indirect_addressing_maps_hardware_error_into_a_block():
  servo = virtual.VirtualServo(1)
  targets = [table.HARDWARE_ERROR_STATUS.address] + list(range(132, 136))
  for n, target in enumerate(targets, start=1):
    item = table.indirect_address(n)
    assert servo.write(item.address, target.to_bytes(2, 'little')) == 0
  servo.set_present(-3000, 0, 0)
  servo.inject_hardware_error(0x04)
  result, data = servo.read(table.indirect_data(1).address, 5)
  assert result == Error.NONE
  assert data[0] == 0x04
  assert table.to_signed(int.from_bytes(data[1:], 'little'), 4) == -3000
  # Writes go to the target too: Torque Enable through Indirect Data 6.
  servo.write(table.indirect_address(6).address, (64).to_bytes(2, 'little'))
  servo.reboot()
  assert servo.write(table.indirect_data(6).address, b'\x01') == Error.NONE
  assert servo.torque_enabled


def test_reg_write_and_action():
  servo = virtual.VirtualServo(1)
  assert servo.action() == Error.INSTRUCTION
  assert servo.reg_write(65, b'\x01') == Error.NONE
  assert servo.get(table.REGISTERED_INSTRUCTION) == 1
  assert servo.get(table.LED) == 0
  assert servo.action() == Error.NONE
  assert servo.get(table.LED) == 1
  assert servo.get(table.REGISTERED_INSTRUCTION) == 0


def test_factory_reset_restores_factory_settings():
  servo = virtual.VirtualServo(12)
  assert servo.factory_reset(protocol.RESET_ALL_BUT_ID) == Error.NONE
  assert servo.motor_id == 12
  assert servo.baud_rate == 57_600
  assert servo.get(table.RETURN_DELAY_TIME) == 250
  assert servo.factory_reset(protocol.RESET_ALL) == Error.NONE
  assert servo.motor_id == 1
  assert servo.factory_reset(0x42) == Error.DATA_RANGE


def test_bus_clear_and_factory_reset_packets():
  bus = virtual.Bus(virtual.make_servos([5]))
  servo = bus.servo(5)

  def send(instruction, params=b'', packet_id=5):
    packet = protocol.encode_instruction(packet_id, instruction, params)
    return protocol.parse(bus.handle(protocol.parse(packet)[0]))

  servo.set_present(2 * 4096 + 100)
  (status,) = send(Instruction.CLEAR, protocol.CLEAR_MULTI_TURN)
  assert status.error == 0 and servo.present_position == 100
  (status,) = send(Instruction.CLEAR, b'\x01')
  assert status.error == Error.INSTRUCTION
  assert send(Instruction.FACTORY_RESET, b'\xff', protocol.BROADCAST_ID) == []
  assert servo.motor_id == 5  # Broadcast reset-all is ignored.
  (status,) = send(Instruction.FACTORY_RESET, b'\x02')
  assert status.id == 5 and status.error == 0
  assert servo.get(table.RETURN_DELAY_TIME) == 250
  (status,) = send(0x07)  # Undefined instruction.
  assert status.error == Error.INSTRUCTION


def test_set_present_rejects_floats_and_overflow():
  servo = virtual.VirtualServo(1)
  with pytest.raises(TypeError):
    servo.set_present(1.5)
  with pytest.raises(ValueError):
    servo.set_present(0, 0, 40_000)


def test_build_bus_for_the_shipped_robots():
  dclaw = virtual_bus.build_bus(config.default('dclaw'))
  assert sorted(dclaw.by_id()) == [10, 11, 12, 20, 21, 22, 30, 31, 32, 50, 60]
  dkitty = virtual_bus.build_bus(config.default('dkitty'))
  assert len(dkitty.servos) == 12
  with pytest.raises(ValueError):
    virtual_bus.build_bus(config.default('dclaw'), driver='nonsense')
  with pytest.raises(ValueError):
    virtual.Bus(virtual.make_servos([1, 1]))


_COMMAND = [sys.executable, '-m', 'robel_dm.commands.virtual_bus']


@pytest.mark.slow
@pytest.mark.parametrize('stop', [signal.SIGINT, signal.SIGTERM])
def test_the_command_serves_until_a_stop_signal_then_ends_cleanly(stop):
  process = subprocess.Popen(
    [*_COMMAND, '--robot=dclaw', '--driver=ideal'],
    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
  )  # fmt: skip
  try:
    ready, _, _ = select.select([process.stdout], [], [], 120)
    assert ready, 'the virtual bus printed no device path'
    assert process.stdout.readline().startswith('/dev/pts/')
    process.send_signal(stop)
    assert process.wait(60) == 0, process.stderr.read()
  finally:
    if process.poll() is None:
      process.kill()
      process.wait()


@pytest.mark.slow
def test_the_standalone_bus_serves_a_robot_and_refuses_a_model_it_lacks():
  with virtual.standalone_bus('dclaw', driver='ideal') as device:
    port = sdk.PortHandler(device)
    assert port.openPort()
    model, result, _ = sdk.PacketHandler(2.0).ping(port, 10)
    port.closePort()
    assert result == sdk.COMM_SUCCESS and model == 1040
  assert not os.path.exists(device)  # Stopped: its terminal is gone.
  bad = virtual.standalone_bus('dclaw', driver='sim', dynamics='none.json')
  with pytest.raises(RuntimeError, match='did not start'), bad:
    pass
  result = subprocess.run(
    [*_COMMAND, '--driver=ideal', '--model_number=1060'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert result.returncode != 0
  assert '--model_number=1060' in result.stderr and '1030' in result.stderr
