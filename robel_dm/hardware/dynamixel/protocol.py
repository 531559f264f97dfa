"""Dynamixel Protocol 2.0 packets: CRC, byte stuffing, encoding, parsing.

Both directions share one frame layout (docs/dynamixel.md section 1.1):

  instruction: FF FF FD 00 | ID | LEN_L LEN_H | INST | params      | CRC
  status:      FF FF FD 00 | ID | LEN_L LEN_H | 0x55 | ERR | params | CRC

LEN counts the (stuffed) bytes after itself, CRC included. The CRC-16
(polynomial 0x8005, initial value 0, not reflected) covers everything from
the first FF to the last parameter as sent, stuffing included, and is sent
low byte first. Stuffing inserts an FD after every FF FF FD in the
instruction byte and the parameters, so that a header never appears inside
a packet.

Fast Sync/Bulk Read replies (0x8A/0x9A) are one status packet from ID 0xFE
made of per-device blocks [ERR, ID, data, CRC]; each block's CRC is the
running CRC of the packet so far, and these packets are never stuffed.

`encode_progress` and `decode_progress` are how a virtual bus on a
pseudo-terminal tells its clients how far it has got.
"""

from collections.abc import Iterable, Sequence
import dataclasses
import enum
import struct

HEADER = b'\xff\xff\xfd\x00'
_HEADER_PREFIX = b'\xff\xff\xfd'
_STUFFING = 0xFD
# Bytes before the stuffed part: header (4), ID (1), LEN (2).
PREAMBLE_SIZE = 7
BROADCAST_ID = 0xFE
MAX_ID = 252
# The SDK refuses to send frames longer than this; the parser rejects them.
MAX_PACKET_SIZE = 1024


class Instruction(enum.IntEnum):
  """Instruction codes (docs/dynamixel.md section 1.4)."""

  PING = 0x01
  READ = 0x02
  WRITE = 0x03
  REG_WRITE = 0x04
  ACTION = 0x05
  FACTORY_RESET = 0x06
  REBOOT = 0x08
  CLEAR = 0x10
  STATUS = 0x55
  SYNC_READ = 0x82
  SYNC_WRITE = 0x83
  FAST_SYNC_READ = 0x8A
  BULK_READ = 0x92
  BULK_WRITE = 0x93
  FAST_BULK_READ = 0x9A


class Error(enum.IntEnum):
  """Result numbers in bits 0-6 of a status packet's error byte."""

  NONE = 0
  RESULT_FAIL = 1
  INSTRUCTION = 2
  CRC = 3
  DATA_RANGE = 4
  DATA_LENGTH = 5
  DATA_LIMIT = 6
  ACCESS = 7


# Bit 7 of the error byte: the device has a latched hardware error (the same
# value as control_table.ALERT_BIT).
ALERT_BIT = 0x80

# Factory Reset options.
RESET_ALL = 0xFF
RESET_ALL_BUT_ID = 0x01
RESET_ALL_BUT_ID_AND_BAUD = 0x02

# Parameters of the Clear instruction (reset the multi-turn position).
CLEAR_MULTI_TURN = b'\x01\x44\x58\x4c\x22'


def _crc_table() -> tuple[int, ...]:
  table = []
  for byte in range(256):
    crc = byte << 8
    for _ in range(8):
      crc = (crc << 1) ^ 0x8005 if crc & 0x8000 else crc << 1
    table.append(crc & 0xFFFF)
  return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
  """Protocol 2.0 CRC-16 of `data`, continuing from `crc`.

  Args:
    data: the bytes to cover.
    crc: the CRC of the bytes before `data` (0 to start).

  Returns:
    The 16-bit CRC (0xFEE8 for b'123456789').
  """
  table = _CRC_TABLE
  for byte in data:
    crc = ((crc << 8) ^ table[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
  return crc


def stuff(data: bytes | bytearray) -> bytes:
  """Inserts an FD after every FF FF FD of the instruction and parameters.

  The SDK also looks back into the LEN bytes while scanning the first two
  bytes; that can only matter for LEN >= 0xFF00, far beyond any legal packet,
  so the body alone is scanned here.

  Args:
    data: instruction byte and parameters (status: also the error byte).

  Returns:
    The stuffed bytes.
  """
  if _HEADER_PREFIX not in data:
    return bytes(data)
  out = bytearray()
  for byte in data:
    out.append(byte)
    if byte == _STUFFING and out[-3:] == _HEADER_PREFIX:
      out.append(_STUFFING)
  return bytes(out)


def unstuff(data: bytes | bytearray) -> bytes:
  """Removes the FD inserted after every FF FF FD (inverse of `stuff`)."""
  if _HEADER_PREFIX not in data:
    return bytes(data)
  out = bytearray()
  for i, byte in enumerate(data):
    if byte == _STUFFING and i >= 3 and data[i - 3 : i] == _HEADER_PREFIX:
      continue
    out.append(byte)
  return bytes(out)


def _check_id(packet_id: int) -> None:
  if not (0 <= packet_id <= MAX_ID or packet_id == BROADCAST_ID):
    raise ValueError(f'packet ID must be 0..{MAX_ID} or 254, got {packet_id}')


def encode_packet(packet_id: int, body: bytes | bytearray) -> bytes:
  """Frames `body` (instruction byte and parameters): stuffing, LEN, CRC.

  Args:
    packet_id: device ID, or BROADCAST_ID.
    body: the instruction byte (0x55 for status) and the parameters.

  Returns:
    The packet as sent on the wire.

  Raises:
    ValueError: for an invalid ID or a packet longer than MAX_PACKET_SIZE.
  """
  _check_id(packet_id)
  stuffed = stuff(body)
  length = len(stuffed) + 2
  if PREAMBLE_SIZE + length > MAX_PACKET_SIZE:
    raise ValueError(f'packet of {PREAMBLE_SIZE + length} bytes is too long')
  frame = bytearray(HEADER)
  frame.append(packet_id)
  frame += length.to_bytes(2, 'little')
  frame += stuffed
  frame += crc16(frame).to_bytes(2, 'little')
  return bytes(frame)


def encode_instruction(
  packet_id: int, instruction: int, params: bytes | bytearray = b''
) -> bytes:
  """An instruction packet.

  Args:
    packet_id: device ID, or BROADCAST_ID.
    instruction: an `Instruction` code.
    params: the parameters, unstuffed.

  Returns:
    The packet as sent on the wire.
  """
  return encode_packet(packet_id, bytes([instruction]) + bytes(params))


def encode_status(
  packet_id: int, error: int, params: bytes | bytearray = b''
) -> bytes:
  """A status packet.

  Args:
    packet_id: the answering device's ID.
    error: the error byte (result number, plus ALERT_BIT if any).
    params: the returned data, unstuffed.

  Returns:
    The packet as sent on the wire.
  """
  body = bytes([Instruction.STATUS, error]) + bytes(params)
  return encode_packet(packet_id, body)


class FastStatusEncoder:
  """Builds a Fast Sync/Bulk Read reply block by block.

  The preamble declares the length of all expected blocks. Each block's CRC
  is the running CRC of the bytes actually emitted before it, so a corrupted
  block CRC stays in the running CRC (as on a shared wire), and a reply with
  fewer blocks than declared is an incomplete packet (a device that did not
  answer).
  """

  def __init__(self, data_lengths: Sequence[int]):
    """Starts a reply.

    Args:
      data_lengths: the data length of every expected block, in order.
    """
    length = 1 + sum(n + 4 for n in data_lengths)
    self._out = bytearray(HEADER)
    self._out.append(BROADCAST_ID)
    self._out += length.to_bytes(2, 'little')
    self._out.append(Instruction.STATUS)
    self._crc = crc16(self._out)

  def add(
    self, error: int, device_id: int, data: bytes, corrupt: bool = False
  ) -> None:
    """Appends one device's block; `corrupt` sends a wrong CRC."""
    block = bytes([error, device_id]) + bytes(data)
    self._crc = crc16(block, self._crc)
    crc = self._crc ^ 0xFFFF if corrupt else self._crc
    crc_bytes = crc.to_bytes(2, 'little')
    self._crc = crc16(crc_bytes, self._crc)
    self._out += block + crc_bytes

  def to_bytes(self) -> bytes:
    return bytes(self._out)


def encode_fast_status(blocks: Iterable[tuple[int, int, bytes]]) -> bytes:
  """A complete Fast Sync/Bulk Read reply from (error, ID, data) blocks."""
  blocks = list(blocks)
  encoder = FastStatusEncoder([len(data) for _, _, data in blocks])
  for error, device_id, data in blocks:
    encoder.add(error, device_id, data)
  return encoder.to_bytes()


@dataclasses.dataclass(frozen=True)
class Packet:
  """A parsed packet.

  Attributes:
    id: the packet's ID (254 = broadcast).
    instruction: the instruction byte (0x55 for a status packet).
    params: the parameters, unstuffed (status: error byte first).
    crc_ok: False if the CRC did not match; the other fields are then only
      a best guess from the bytes received.
  """

  id: int
  instruction: int
  params: bytes = b''
  crc_ok: bool = True

  @property
  def is_status(self) -> bool:
    return self.instruction == Instruction.STATUS

  @property
  def error(self) -> int:
    """A status packet's error byte."""
    if not self.is_status or not self.params:
      raise ValueError('not a status packet')
    return self.params[0]

  @property
  def data(self) -> bytes:
    """A status packet's data (the parameters after the error byte)."""
    if not self.is_status or not self.params:
      raise ValueError('not a status packet')
    return self.params[1:]


class PacketParser:
  """Incremental parser of a Protocol 2.0 byte stream.

  `feed` accepts bytes in any fragmentation and returns the packets they
  complete. Bytes that do not belong to a packet are skipped (counted in
  `discarded`): a packet starts at FF FF FD 00 followed by a valid ID and a
  LEN of 3..MAX_PACKET_SIZE - 7. A frame whose CRC does not match is
  returned with `crc_ok=False`; then only its header is consumed, so a
  corrupted LEN cannot swallow the packets after it. A false header whose
  LEN runs past the data received stalls the stream until more bytes
  arrive; `resync()` abandons it.
  """

  def __init__(self, max_packet_size: int = MAX_PACKET_SIZE):
    self._buffer = bytearray()
    self._max_length = max_packet_size - PREAMBLE_SIZE
    self.discarded = 0

  @property
  def pending(self) -> int:
    """Bytes received but not yet part of a complete packet."""
    return len(self._buffer)

  def feed(self, data: bytes | bytearray) -> list[Packet]:
    """Adds received bytes; returns the packets completed, in order."""
    self._buffer += data
    return self._drain()

  def resync(self) -> list[Packet]:
    """Abandons the partial packet at the front of the buffer.

    Returns:
      Packets found in the bytes after its first byte.
    """
    if self._buffer:
      self._drop(1)
    return self._drain()

  def _drop(self, count: int) -> None:
    del self._buffer[:count]
    self.discarded += count

  def _drain(self) -> list[Packet]:
    packets = []
    buffer = self._buffer
    while buffer:
      start = buffer.find(_HEADER_PREFIX)
      if start < 0:
        # Keep a trailing FF or FF FF: it may start the next header.
        keep = 0
        while keep < min(2, len(buffer)) and buffer[-1 - keep] == 0xFF:
          keep += 1
        self._drop(len(buffer) - keep)
        break
      if start:
        self._drop(start)
      if len(buffer) < PREAMBLE_SIZE:
        break
      packet_id = buffer[4]
      length = buffer[5] | buffer[6] << 8
      if (
        buffer[3] != 0
        or packet_id in (0xFD, 0xFF)
        or not 3 <= length <= self._max_length
      ):
        self._drop(1)
        continue
      size = PREAMBLE_SIZE + length
      if len(buffer) < size:
        break
      frame = bytes(buffer[:size])
      crc_ok = crc16(frame[:-2]) == frame[-2] | frame[-1] << 8
      body = unstuff(frame[PREAMBLE_SIZE:-2])
      packets.append(Packet(packet_id, body[0], body[1:], crc_ok))
      if crc_ok:
        del buffer[:size]
      else:
        self._drop(len(_HEADER_PREFIX))
    return packets


def parse(data: bytes | bytearray) -> list[Packet]:
  """All complete packets in `data` (a convenience for one-shot parsing)."""
  return PacketParser().feed(data)


# --- A virtual bus's progress, on its pseudo-terminal -------------------------

# A virtual bus served on a pseudo-terminal (`virtual.transport`) keeps the
# count of bytes sent to it that it has answered in the pty's window size,
# which means nothing on a serial line: a client in any process reads it at
# its end (TIOCGWINSZ) and so tells a bus that a busy machine holds up from
# a silent motor. Its four 16-bit fields hold the count's low 48 bits, low
# word first, then this mark.
PROGRESS_MARK = 0x5242
_WINSIZE = struct.Struct('=4H')  # struct winsize: rows, columns, x, y.


def encode_progress(answered: int) -> bytes:
  """The window size (struct winsize) that publishes `answered` bytes."""
  count = answered & 0xFFFF_FFFF_FFFF
  return _WINSIZE.pack(
    count & 0xFFFF, count >> 16 & 0xFFFF, count >> 32, PROGRESS_MARK
  )


def decode_progress(winsize: bytes) -> int | None:
  """The count a window size publishes; None if it publishes none."""
  low, middle, high, mark = _WINSIZE.unpack(winsize)
  if mark != PROGRESS_MARK:
    return None
  return low | middle << 16 | high << 32
