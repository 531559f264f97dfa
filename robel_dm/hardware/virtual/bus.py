"""Servos sharing one bus: the instruction packets they execute.

`Bus` executes instruction packets on the servos: Ping, Read, Write, Reg
Write, Action, Factory Reset, Reboot, Clear, Sync/Bulk Read and Write, and
Fast Sync/Bulk Read, with the Status Return Level and broadcast rules. A
`Driver` moves the motors (`IdealDriver` by default; a physics simulation
can take its place), and `faults.Faults` injects communication failures at
runtime. The bus is transport-free: `transport.PtyBusServer` puts it on a
pseudo-terminal.

Behaviour the e-manual leaves open, chosen here (docs/dynamixel.md marks these
unverified): an instruction with a bad CRC is answered with error 3; the
reply to Reboot and Factory Reset describes the state before the reset;
malformed parameters give error 2 (Instruction). Not modelled: any dynamics
beyond what the driver does.
"""

import collections
from collections.abc import Callable, Iterable, Mapping, Sequence
import dataclasses
import threading
from typing import Protocol

from robel_dm.hardware import config
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Error, Instruction
from robel_dm.hardware.virtual.faults import Faults
from robel_dm.hardware.virtual.servo import VirtualServo


class Driver(Protocol):
  """Moves the motors: the bus calls it with its lock held.

  `servos` maps every servo's current ID to the servo; `ids` are the IDs
  concerned. A driver reads goals and torque from the servos and sets their
  present state (`VirtualServo.set_present`); it must not block for long.
  """

  def on_write(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    """Called after an instruction changed these servos.

    That is a successful Write, Sync/Bulk Write or Action, a Reboot, Factory
    Reset or Clear; a write refused with an error does not count.
    """

  def on_read(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    """Called before a read or sync/bulk read of these servos is answered."""


class IdealDriver:
  """Perfect servos: with torque on, a motor is at its goal at once.

  With torque on the present position equals the Goal Position, velocity and
  current are 0; with torque off the motor holds its position. The operating
  mode is ignored.
  """

  def on_write(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    for motor_id in ids:
      servo = servos[motor_id]
      if servo.torque_enabled:
        servo.set_present(servo.goal_position, 0, 0)

  def on_read(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    del servos, ids  # The state only changes on writes.


_READS = frozenset(
  {
    Instruction.READ,
    Instruction.SYNC_READ,
    Instruction.FAST_SYNC_READ,
    Instruction.BULK_READ,
    Instruction.FAST_BULK_READ,
  }
)


@dataclasses.dataclass
class _Reply:
  servo: VirtualServo
  reply_id: int
  error: int
  data: bytes = b''


class Bus:
  """Servos sharing one bus: executes instruction packets.

  Transport-free: `handle` takes a parsed packet and returns the bytes the
  servos send back. `PtyBusServer` puts it on a pseudo-terminal.

  Attributes:
    lock: held while a packet is handled (and by the servos' helpers).
    driver: moves the motors.
    faults: the communication faults to inject.
    stats: Counter of 'packets', 'crc_errors' and 'replies' (status
      packets sent).
  """

  def __init__(
    self,
    servos: Iterable[VirtualServo],
    driver: Driver | None = None,
    faults: Faults | None = None,
  ):
    """Initializes the bus.

    Args:
      servos: the servos on the bus (IDs must differ).
      driver: moves the motors; an `IdealDriver` by default.
      faults: communication faults; none by default.

    Raises:
      ValueError: if two servos have the same ID.
    """
    self.lock = threading.RLock()
    self._servos = tuple(servos)
    ids = [servo.motor_id for servo in self._servos]
    if len(set(ids)) != len(ids):
      raise ValueError(f'servo IDs must differ: {ids}')
    for servo in self._servos:
      servo.lock = self.lock
    self.driver: Driver = driver if driver is not None else IdealDriver()
    self.faults = faults if faults is not None else Faults()
    self.stats: collections.Counter[str] = collections.Counter()

  @property
  def servos(self) -> tuple[VirtualServo, ...]:
    return self._servos

  def by_id(self) -> dict[int, VirtualServo]:
    """Servos by their current ID (the register: writes may change it)."""
    with self.lock:
      servos = {}
      for servo in self._servos:
        servos.setdefault(servo.motor_id, servo)
      return servos

  def servo(self, motor_id: int) -> VirtualServo:
    """The servo with this ID.

    Raises:
      KeyError: if there is none.
    """
    servo = self.by_id().get(motor_id)
    if servo is None:
      raise KeyError(f'no servo with ID {motor_id}')
    return servo

  __getitem__ = servo

  def goal_positions(self) -> dict[int, int]:
    """The last accepted Goal Position of every servo, ticks."""
    with self.lock:
      return {i: s.goal_position for i, s in self.by_id().items()}

  def handle(
    self, packet: protocol.Packet, baud_rate: int | None = None
  ) -> bytes:
    """Executes one packet.

    Args:
      packet: a parsed packet (status packets are ignored).
      baud_rate: the sender's bit rate; servos set to another rate do not
        hear the packet. None: everyone hears it.

    Returns:
      The status packets sent back, concatenated (possibly empty).
    """
    with self.lock:
      self.stats['packets'] += 1
      if packet.is_status:
        return b''
      if not packet.crc_ok:
        self.stats['crc_errors'] += 1
        replies = self._crc_error(packet, baud_rate)
      else:
        handler = self._HANDLERS.get(packet.instruction)
        replies = (
          self._unknown(packet, baud_rate)
          if handler is None
          else handler(self, packet, baud_rate)
        )
      if isinstance(replies, bytes):
        return replies
      return b''.join(self._encode(reply) for reply in replies)

  # --- Helpers ---------------------------------------------------------------

  def _addressed(self, packet_id: int) -> list[VirtualServo]:
    if packet_id == protocol.BROADCAST_ID:
      return sorted(self._servos, key=lambda servo: servo.motor_id)
    return [s for s in self._servos if s.motor_id == packet_id]

  def _listen(
    self,
    servo: VirtualServo,
    baud_rate: int | None,
    instruction: int | None,
  ) -> bool:
    """Whether the servo receives the packet (counts it if so)."""
    motor_id = servo.motor_id
    if self.faults.is_absent(motor_id):
      return False
    if baud_rate is not None and servo.baud_rate != baud_rate:
      return False
    if self.faults.take_mute(motor_id):
      return False
    if instruction is not None:
      servo.counters[instruction] += 1
    return True

  @staticmethod
  def _answers(servo: VirtualServo, instruction: int) -> bool:
    if instruction == Instruction.PING:
      return True
    level = servo.status_return_level
    return level >= 1 if instruction in _READS else level >= 2

  def _encode(self, reply: _Reply) -> bytes:
    packet = protocol.encode_status(reply.reply_id, reply.error, reply.data)
    if self.faults.take_corrupt(reply.servo.motor_id):
      packet = packet[:-2] + bytes([packet[-2] ^ 0xFF, packet[-1]])
    self.stats['replies'] += 1
    return packet

  def _wrote(self, ids: list[int]) -> None:
    if ids:
      self.driver.on_write(self.by_id(), ids)

  def _simple(
    self,
    packet: protocol.Packet,
    baud_rate: int | None,
    execute: Callable[[VirtualServo], int],
    touches: bool = True,
  ) -> list[_Reply]:
    """Runs a unicast/broadcast instruction answered by an empty status."""
    broadcast = packet.id == protocol.BROADCAST_ID
    replies, touched = [], []
    for servo in self._addressed(packet.id):
      if not self._listen(servo, baud_rate, packet.instruction):
        continue
      answers = not broadcast and self._answers(servo, packet.instruction)
      # The alert bit as the instruction arrives (e.g. before a reboot).
      alert = servo.status_error(Error.NONE)
      result = execute(servo)
      if result == Error.NONE and touches:
        touched.append(servo.motor_id)
      if answers:
        replies.append(_Reply(servo, packet.id, alert | result))
    self._wrote(touched)
    return replies

  def _malformed(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    """Unicast: Instruction error; broadcast: ignored."""
    return self._simple(packet, baud_rate, lambda _: Error.INSTRUCTION, False)

  # --- Instructions ----------------------------------------------------------

  def _crc_error(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if packet.id == protocol.BROADCAST_ID:
      return []
    replies = []
    for servo in self._addressed(packet.id):
      if self._listen(servo, baud_rate, None):
        servo.crc_errors += 1
        if self._answers(servo, packet.instruction):
          error = servo.status_error(Error.CRC)
          replies.append(_Reply(servo, packet.id, error))
    return replies

  def _unknown(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    return self._malformed(packet, baud_rate)

  def _ping(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    replies = []
    for servo in self._addressed(packet.id):
      if self._listen(servo, baud_rate, Instruction.PING):
        data = servo.model_number.to_bytes(2, 'little')
        data += bytes([servo.firmware])
        error = servo.status_error(Error.NONE)
        replies.append(_Reply(servo, servo.motor_id, error, data))
    return replies

  def _read(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if packet.id == protocol.BROADCAST_ID:  # Executed by nobody, unanswered.
      for servo in self._servos:
        self._listen(servo, baud_rate, Instruction.READ)
      return []
    if len(packet.params) != 4:
      return self._malformed(packet, baud_rate)
    address = int.from_bytes(packet.params[:2], 'little')
    length = int.from_bytes(packet.params[2:], 'little')
    replies = []
    for servo in self._addressed(packet.id):
      if not self._listen(servo, baud_rate, Instruction.READ):
        continue
      self.driver.on_read(self.by_id(), [servo.motor_id])
      result, data = servo.read(address, length)
      if self._answers(servo, Instruction.READ):
        error = servo.status_error(result)
        replies.append(_Reply(servo, packet.id, error, data))
    return replies

  def _write(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if len(packet.params) < 3:
      return self._malformed(packet, baud_rate)
    address = int.from_bytes(packet.params[:2], 'little')
    data = packet.params[2:]
    if packet.instruction == Instruction.REG_WRITE:
      return self._simple(
        packet, baud_rate, lambda s: s.reg_write(address, data), False
      )
    return self._simple(packet, baud_rate, lambda s: s.write(address, data))

  def _action(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    return self._simple(packet, baud_rate, VirtualServo.action)

  def _reboot(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    def reboot(servo: VirtualServo) -> int:
      servo.reboot()
      return Error.NONE

    return self._simple(packet, baud_rate, reboot)

  def _factory_reset(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if len(packet.params) != 1:
      return self._malformed(packet, baud_rate)
    option = packet.params[0]
    if packet.id == protocol.BROADCAST_ID and option == protocol.RESET_ALL:
      return self._simple(packet, baud_rate, lambda _: Error.NONE, False)
    return self._simple(packet, baud_rate, lambda s: s.factory_reset(option))

  def _clear(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if packet.params != protocol.CLEAR_MULTI_TURN:
      return self._malformed(packet, baud_rate)
    return self._simple(packet, baud_rate, VirtualServo.clear_multi_turn)

  def _sync_read(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply] | bytes:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID or len(params) < 5:
      return []
    address = int.from_bytes(params[:2], 'little')
    length = int.from_bytes(params[2:4], 'little')
    requests = [(i, address, length) for i in dict.fromkeys(params[4:])]
    return self._group_read(packet.instruction, requests, baud_rate)

  def _bulk_read(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply] | bytes:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID or not params or len(params) % 5:
      return []
    requests = {}
    for start in range(0, len(params), 5):
      entry = params[start : start + 5]
      address = int.from_bytes(entry[1:3], 'little')
      requests.setdefault(
        entry[0], (entry[0], address, int.from_bytes(entry[3:], 'little'))
      )
    return self._group_read(
      packet.instruction, list(requests.values()), baud_rate
    )

  def _group_read(
    self,
    instruction: int,
    requests: list[tuple[int, int, int]],
    baud_rate: int | None,
  ) -> list[_Reply] | bytes:
    """Sync/bulk reads: the servos answer in request order."""
    servos = self.by_id()
    listening = {}
    for motor_id, _, _ in requests:
      servo = servos.get(motor_id)
      if servo is not None and self._listen(servo, baud_rate, instruction):
        listening[motor_id] = servo
    if listening:
      self.driver.on_read(servos, list(listening))
    replies = []
    for motor_id, address, length in requests:
      servo = listening.get(motor_id)
      if servo is None or not self._answers(servo, instruction):
        if self.faults.chain_break:
          break  # The next servo waits for a packet that never comes.
        continue
      result, data = servo.read(address, length)
      replies.append(_Reply(servo, motor_id, servo.status_error(result), data))
    fast = instruction in (
      Instruction.FAST_SYNC_READ,
      Instruction.FAST_BULK_READ,
    )
    if not fast:
      return replies
    if not replies:
      return b''
    encoder = protocol.FastStatusEncoder([length for _, _, length in requests])
    lengths = {motor_id: length for motor_id, _, length in requests}
    for reply in replies:
      data = reply.data.ljust(lengths[reply.reply_id], b'\0')
      corrupt = self.faults.take_corrupt(reply.reply_id)
      encoder.add(reply.error, reply.reply_id, data, corrupt)
    self.stats['replies'] += 1
    return encoder.to_bytes()

  def _sync_write(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID or len(params) < 4:
      return []
    address = int.from_bytes(params[:2], 'little')
    length = int.from_bytes(params[2:4], 'little')
    body = params[4:]
    if length == 0 or not body or len(body) % (length + 1):
      return []
    writes = [
      (body[i], address, body[i + 1 : i + 1 + length])
      for i in range(0, len(body), length + 1)
    ]
    return self._group_write(packet.instruction, writes, baud_rate)

  def _bulk_write(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID:
      return []
    writes, position = [], 0
    while position < len(params):
      if position + 5 > len(params):
        return []
      motor_id = params[position]
      address = int.from_bytes(params[position + 1 : position + 3], 'little')
      length = int.from_bytes(params[position + 3 : position + 5], 'little')
      data = params[position + 5 : position + 5 + length]
      if length == 0 or len(data) != length:
        return []
      writes.append((motor_id, address, data))
      position += 5 + length
    return self._group_write(packet.instruction, writes, baud_rate)

  def _group_write(
    self,
    instruction: int,
    writes: list[tuple[int, int, bytes]],
    baud_rate: int | None,
  ) -> list[_Reply]:
    servos = self.by_id()
    touched, seen = [], set()
    for motor_id, address, data in writes:
      servo = servos.get(motor_id)
      if servo is None or motor_id in seen:  # An ID may appear only once.
        continue
      seen.add(motor_id)
      if self.faults.take_lost_write(motor_id):
        continue
      listens = self._listen(servo, baud_rate, instruction)
      if listens and servo.write(address, data) == Error.NONE:
        touched.append(motor_id)
    self._wrote(touched)
    return []

  _HANDLERS = {
    Instruction.PING: _ping,
    Instruction.READ: _read,
    Instruction.WRITE: _write,
    Instruction.REG_WRITE: _write,
    Instruction.ACTION: _action,
    Instruction.FACTORY_RESET: _factory_reset,
    Instruction.REBOOT: _reboot,
    Instruction.CLEAR: _clear,
    Instruction.SYNC_READ: _sync_read,
    Instruction.FAST_SYNC_READ: _sync_read,
    Instruction.BULK_READ: _bulk_read,
    Instruction.FAST_BULK_READ: _bulk_read,
    Instruction.SYNC_WRITE: _sync_write,
    Instruction.BULK_WRITE: _bulk_write,
  }


def robot_motor_ids(robot_config: config.RobotConfig) -> list[int]:
  """Every motor of a robot: joints, then auxiliary motors."""
  return [motor.id for motor in robot_config.joints + robot_config.auxiliary]
