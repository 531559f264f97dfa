"""An OptiTrack Motive NatNet client for the rigid-body stream.

`NatNetClient` is a `tracking.TrackerSource`: a background thread receives
Motive's frame-of-data datagrams over UDP (multicast or unicast), decodes
the rigid bodies and keeps the latest valid pose of each; `poll` returns
the poses received since the previous poll, keyed by the rigid body's
streaming ID as a string ('1', '2', ...).

Wire format (what this module relies on, and where from)
--------------------------------------------------------
All values little-endian. Sources, looked up for this module:
  [A] OptiTrack docs, "NatNet: Data Types" (docs.optitrack.com): frame data
      is sent per frame; rigid-body frame data = ID, position, orientation,
      mean error, parameters (sRigidBodyData in NatNetTypes.h).
  [B] python-natnet documentation, `natnet.protocol.MocapFrameMessage`
      (python-natnet.readthedocs.io): positions are (x, y, z) in metres in
      Motive's frame (Y-up or Z-up per the streaming settings), orientations
      are quaternions (x, y, z, w); from NatNet 3 on, a rigid body no longer
      carries its markers' positions, IDs and sizes.
  [C] natnet-decode documentation (docs.rs): FrameOfData field order frame
      number, named marker sets, other (unlabeled) markers, rigid bodies,
      skeletons, labeled markers, force plates, ...; a rigid body's
      tracking-valid flag exists from NatNet 2.6.
  [D] natnet crate documentation (docs.rs): message header = uint16 message
      ID + uint16 payload size; NAT_FRAMEOFDATA = 7; NAT_KEEPALIVE = 10, a
      liveness message unicast clients send to the command port; supported
      layouts 3.0, 3.1, 4.0 and 4.1, where only 4.1 has per-section byte
      counts (and assets).
  [E] Motive "Data Streaming pane" / "Settings: Streaming" pages and a
      third-party NatNet interface's settings table: command port 1510, data
      port 1511, multicast group 239.255.42.99, multicast or unicast.

Layout decoded here (NatNet 3.0, 3.1, 4.0 and 4.1):

  header    uint16 message ID (7 = frame of data), uint16 payload size
  payload   int32 frame number
            marker sets:       int32 count, [4.1: int32 section bytes],
                               count x (NUL-terminated name, int32 n,
                               n x 3 float32)
            unlabeled markers: int32 n, [4.1: int32 section bytes],
                               n x 3 float32
            rigid bodies:      int32 count, [4.1: int32 section bytes],
                               count x (int32 id, 3 float32 position,
                               4 float32 quaternion x y z w, float32 mean
                               marker error, int16 params; 38 bytes)
            skeletons, [4.1: assets], labeled markers, force plates,
            devices, timing, ...: not decoded (not needed for poses).

The tracking-valid flag is taken as bit 0 of the rigid body's `params`:
[A] defers to NatNetTypes.h for it, and [B], [C] and ROS's mocap_optitrack
name the flag without showing the bit, so the bit number is the one
unconfirmed by the pages found (a wrong bit would drop every body, which
the tracker reports as "no pose received").
Ambiguities: the 4.1 section byte count is documented by [D] for the
data-description message and as a layout-wide feature; that each frame
section carries one after its count is inferred, not confirmed against
Motive, and what it counts is not stated, so the decoder skips it and walks
every section by its element counts.
Versions 3.0, 3.1 and 4.0 have the identical layout above; 2.x (rigid bodies
with marker lists) is not supported. The version is detected from the first
frame unless given (`detect_version`: only 4.1's layout differs). Checked:
the round trip against this module's own encoder for every supported version
(tests/test_tracking.py), and every frame this module encodes decoded by an
independent implementation, the `natnet` package on PyPI, which reads the
tracking-valid flag as bit 0 of `params` and 4.1's byte count after each
section's count as assumed here (tests/test_natnet_independent.py); not
checked against a running Motive.

Unicast: with `server_address`, the client sends a connect request
(NAT_CONNECT, message 0) and then a keep-alive (message 10) every second to
the server's command port, from the data socket, so the server learns where
to send frames. How Motive picks the unicast destination (the requester's
address or the client's data port) is not documented in what was found; the
data socket is bound to the data port, so both work.
"""

from collections.abc import Iterable, Mapping, Sequence
import dataclasses
import logging
import select
import socket
import struct
import threading
import time

import numpy as np

from robel_dm.hardware.tracking import tracker as tracking

NAT_CONNECT = 0
NAT_FRAMEOFDATA = 7
NAT_KEEPALIVE = 10

DEFAULT_COMMAND_PORT = 1510
DEFAULT_DATA_PORT = 1511
DEFAULT_MULTICAST_GROUP = '239.255.42.99'
# NatNet versions whose frame layout this module decodes and encodes.
SUPPORTED_VERSIONS = ((3, 0), (3, 1), (4, 0), (4, 1))
DEFAULT_VERSION = (4, 0)

_HEADER = struct.Struct('<HH')
_INT32 = struct.Struct('<i')
# id, x, y, z, qx, qy, qz, qw, mean marker error, params.
_RIGID_BODY = struct.Struct('<i3f4ffh')
_TRACKING_VALID = 0x01
_MARKER_BYTES = 12  # 3 float32.
_MAX_DATAGRAM = 65535
_KEEPALIVE_INTERVAL = 1.0  # s
_SELECT_TIMEOUT = 0.05  # s; bounds how long `close` waits for the thread.
_ERROR_LOG_INTERVAL = 5.0  # s


class NatNetError(ValueError):
  """A datagram that does not decode as a NatNet frame of this version."""


@dataclasses.dataclass(frozen=True)
class RigidBody:
  """One rigid body of a frame, as streamed.

  Attributes:
    id: Motive's streaming ID.
    position: (x, y, z), m, in Motive's frame.
    quaternion: (w, x, y, z) (NatNet sends x, y, z, w).
    mean_error: mean marker error, m.
    tracking_valid: whether Motive tracked the body in this frame.
  """

  id: int
  position: tuple[float, float, float]
  quaternion: tuple[float, float, float, float]
  mean_error: float = 0.0
  tracking_valid: bool = True


@dataclasses.dataclass(frozen=True)
class Frame:
  """A decoded frame of data (only what this client needs)."""

  frame_number: int
  rigid_bodies: tuple[RigidBody, ...]


def _check_version(version: Sequence[int]) -> tuple[int, int]:
  version = tuple(int(v) for v in version[:2])
  if version not in SUPPORTED_VERSIONS:
    raise ValueError(
      f'NatNet {".".join(map(str, version))} is not supported; supported: '
      f'{", ".join(f"{a}.{b}" for a, b in SUPPORTED_VERSIONS)} (set Motive '
      "'s streaming bitstream version to one of them)"
    )
  return version


def _has_section_sizes(version: tuple[int, int]) -> bool:
  return version >= (4, 1)


class _Reader:
  """Bounds-checked little-endian reads over one payload."""

  def __init__(self, data: bytes):
    self._data = memoryview(data)
    self.offset = 0

  def take(self, size: int) -> memoryview:
    end = self.offset + size
    if size < 0 or end > len(self._data):
      raise NatNetError(
        f'truncated: needs {size} bytes at offset {self.offset} of '
        f'{len(self._data)}'
      )
    view = self._data[self.offset : end]
    self.offset = end
    return view

  def unpack(self, layout: struct.Struct) -> tuple:
    return layout.unpack(self.take(layout.size))

  def count(self, what: str) -> int:
    (value,) = self.unpack(_INT32)
    if value < 0:
      raise NatNetError(f'negative {what} count {value}')
    return value

  def skip_string(self) -> None:
    data = self._data
    for end in range(self.offset, len(data)):
      if data[end] == 0:
        self.offset = end + 1
        return
    raise NatNetError('unterminated marker set name')


def decode_frame(
  payload: bytes, version: Sequence[int] = DEFAULT_VERSION
) -> Frame:
  """Decodes a frame-of-data payload (after the 4-byte message header).

  Args:
    payload: the message's payload.
    version: the NatNet (major, minor) version Motive streams.

  Returns:
    The frame number and its rigid bodies.

  Raises:
    NatNetError: if the payload is truncated or malformed.
    ValueError: for an unsupported version.
  """
  version = _check_version(version)
  sized = _has_section_sizes(version)
  reader = _Reader(payload)
  (frame_number,) = reader.unpack(_INT32)
  # 4.1's section byte counts are read past, not trusted: the sections are
  # walked by their element counts in every version, so what exactly the
  # byte count covers (undocumented in what was found) does not matter.
  # Named marker sets: skipped.
  marker_sets = reader.count('marker set')
  if sized:
    reader.unpack(_INT32)
  for _ in range(marker_sets):
    reader.skip_string()
    reader.take(_MARKER_BYTES * reader.count('marker'))
  # Unlabeled ("other") markers: skipped.
  markers = reader.count('unlabeled marker')
  if sized:
    reader.unpack(_INT32)
  reader.take(_MARKER_BYTES * markers)
  count = reader.count('rigid body')
  if sized:
    reader.unpack(_INT32)
  bodies = []
  for _ in range(count):
    body_id, x, y, z, qx, qy, qz, qw, error, params = reader.unpack(_RIGID_BODY)
    bodies.append(
      RigidBody(
        id=body_id,
        position=(x, y, z),
        quaternion=(qw, qx, qy, qz),
        mean_error=error,
        tracking_valid=bool(params & _TRACKING_VALID),
      )
    )
  return Frame(frame_number, tuple(bodies))


def detect_version(payload: bytes) -> tuple[int, int]:
  """Which layout a frame-of-data payload has: (4, 1) (sections carry byte
  counts) or (4, 0) (the layout 3.0, 3.1 and 4.0 share).

  A payload is taken as 4.1 when every byte count of the sections decoded
  here equals the bytes its section holds; a 4.0 payload read that way
  fails that check (its first "byte count" is the next section's data).

  Raises:
    NatNetError: if the payload fits neither layout.
  """
  reader = _Reader(payload)
  try:
    reader.unpack(_INT32)  # Frame number.
    consistent = True
    marker_sets = reader.count('marker set')
    (size,) = reader.unpack(_INT32)
    start = reader.offset
    for _ in range(marker_sets):
      reader.skip_string()
      reader.take(_MARKER_BYTES * reader.count('marker'))
    consistent &= reader.offset - start == size
    markers = reader.count('unlabeled marker')
    (size,) = reader.unpack(_INT32)
    consistent &= size == _MARKER_BYTES * markers
    reader.take(_MARKER_BYTES * markers)
    bodies = reader.count('rigid body')
    (size,) = reader.unpack(_INT32)
    consistent &= size == _RIGID_BODY.size * bodies
    reader.take(_RIGID_BODY.size * bodies)
  except NatNetError:
    consistent = False
  if consistent:
    return (4, 1)
  decode_frame(payload, (4, 0))  # Raises if it is not 4.0 either.
  return (4, 0)


def decode_message(
  datagram: bytes, version: Sequence[int] = DEFAULT_VERSION
) -> Frame | None:
  """Decodes a datagram: a `Frame`, or None for another message type.

  Raises:
    NatNetError: if it is malformed.
  """
  if len(datagram) < _HEADER.size:
    raise NatNetError(f'{len(datagram)}-byte datagram has no header')
  message_id, size = _HEADER.unpack_from(datagram)
  if message_id != NAT_FRAMEOFDATA:
    return None
  payload = datagram[_HEADER.size :]
  if size > len(payload):
    raise NatNetError(
      f'header announces {size} payload bytes, datagram has {len(payload)}'
    )
  # The sections decoded come first, so trailing bytes do not matter (and
  # the 16-bit size cannot describe a frame over 64 KiB anyway).
  return decode_frame(payload, version)


def _section(count: int, body: bytes, sized: bool) -> bytes:
  prefix = _INT32.pack(count)
  if sized:
    prefix += _INT32.pack(len(body))
  return prefix + body


def encode_frame(
  frame_number: int,
  rigid_bodies: Iterable[RigidBody],
  *,
  marker_sets: Mapping[str, Sequence[Sequence[float]]] | None = None,
  unlabeled_markers: Sequence[Sequence[float]] = (),
  version: Sequence[int] = DEFAULT_VERSION,
) -> bytes:
  """Encodes a frame-of-data datagram (header included), e.g. for tests.

  The sections `decode_frame` reads are laid out as documented above. The
  tail (empty skeleton, [asset,] labeled-marker, force-plate and device
  sections, then 46 zeroed bytes standing for the timing fields) is a
  placeholder, not byte-checked against Motive; `decode_frame` does not
  read it.

  Args:
    frame_number: Motive's frame counter.
    rigid_bodies: the bodies (quaternions w, x, y, z).
    marker_sets: name -> marker positions (x, y, z).
    unlabeled_markers: positions (x, y, z).
    version: the NatNet (major, minor) version.

  Returns:
    The datagram.
  """
  version = _check_version(version)
  sized = _has_section_sizes(version)
  marker_sets = marker_sets or {}
  payload = _INT32.pack(frame_number)
  sets = b''
  for name, markers in marker_sets.items():
    sets += name.encode() + b'\0' + _INT32.pack(len(markers))
    sets += b''.join(struct.pack('<3f', *m) for m in markers)
  payload += _section(len(marker_sets), sets, sized)
  payload += _section(
    len(unlabeled_markers),
    b''.join(struct.pack('<3f', *m) for m in unlabeled_markers),
    sized,
  )
  rigid_bodies = tuple(rigid_bodies)
  bodies = b''
  for body in rigid_bodies:
    w, x, y, z = body.quaternion
    bodies += _RIGID_BODY.pack(
      body.id,
      *body.position,
      x,
      y,
      z,
      w,
      body.mean_error,
      _TRACKING_VALID if body.tracking_valid else 0,
    )
  payload += _section(len(rigid_bodies), bodies, sized)
  # Skeletons, [assets,] labeled markers, force plates, devices.
  for _ in range(5 if sized else 4):
    payload += _section(0, b'', sized)
  # Timing placeholder: timecode, subframe, timestamp, three clocks,
  # params, end of data.
  payload += struct.pack('<IIdQQQhi', 0, 0, 0.0, 0, 0, 0, 0, 0)
  return _HEADER.pack(NAT_FRAMEOFDATA, len(payload) & 0xFFFF) + payload


def encode_request(message_id: int, text: str = '') -> bytes:
  """A client request: header + NUL-terminated text (empty for keep-alive)."""
  body = text.encode() + b'\0' if text else b''
  return _HEADER.pack(message_id, len(body)) + body


class NatNetClient:
  """Receives Motive's rigid bodies; a `tracking.TrackerSource`.

  Use as a context manager, or call `close`. Poses are in Motive's frame
  (Y-up by default: give `TorsoTracker`
  `frames=Frames(frame_rotation=Y_UP_TO_Z_UP)`);
  their timestamp is the monotonic receive time. Bodies Motive reports as
  not tracked are dropped (the last valid pose then ages and a
  `TorsoTracker` reports it stale).
  """

  def __init__(
    self,
    *,
    multicast_group: str | None = DEFAULT_MULTICAST_GROUP,
    data_port: int = DEFAULT_DATA_PORT,
    local_interface: str = '0.0.0.0',
    server_address: str | None = None,
    command_port: int = DEFAULT_COMMAND_PORT,
    version: Sequence[int] | None = None,
    clock=time.monotonic,
  ):
    """Opens the data socket and starts the receiver thread.

    Args:
      multicast_group: the group Motive streams to; None for unicast.
      data_port: the local UDP port frames arrive on (0: any free port,
        for unicast; see `address`).
      local_interface: the local IPv4 address to bind and, for multicast,
        to join the group on ('0.0.0.0': any).
      server_address: Motive's IPv4 address. For unicast the client
        subscribes (connect request, then keep-alives) to it; datagrams
        from other hosts are ignored.
      command_port: Motive's command port.
      version: NatNet (major, minor) version Motive streams (its
        "bitstream version"); 3.0, 3.1, 4.0 and 4.1 are supported. None
        (default): detected from the first frame (`detect_version`).
      clock: the receive-time clock (seconds).

    Raises:
      ValueError: for an unsupported version.
      OSError: if the socket cannot be opened or the group joined.
    """
    self._version = None if version is None else _check_version(version)
    self._clock = clock
    self._server = (
      (server_address, command_port) if server_address is not None else None
    )
    self._multicast = multicast_group
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
      sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
      if multicast_group is not None:
        # Bind the port on every address so group datagrams are delivered.
        sock.bind(('', data_port))
        membership = socket.inet_aton(multicast_group) + socket.inet_aton(
          local_interface
        )
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
      else:
        sock.bind((local_interface, data_port))
      sock.setblocking(False)
    except BaseException:
      sock.close()
      raise
    self._socket = sock
    self._address = sock.getsockname()
    self._lock = threading.Lock()
    self._latest: dict[int, tracking.Pose] = {}
    self._new: set[int] = set()
    self._stats = {'frames': 0, 'malformed': 0, 'other': 0, 'invalid': 0}
    self._last_error = ''
    self._last_error_log = -np.inf
    self._stop = threading.Event()
    self._next_keepalive = 0.0
    if self._server is not None and multicast_group is None:
      self._send(encode_request(NAT_CONNECT, 'Ping'))
      self._next_keepalive = time.monotonic() + _KEEPALIVE_INTERVAL
    self._thread = threading.Thread(
      target=self._run, name='natnet-receiver', daemon=True
    )
    self._thread.start()

  @property
  def address(self) -> tuple[str, int]:
    """The data socket's local (address, port)."""
    return self._address

  @property
  def version(self) -> tuple[int, int] | None:
    """The stream's NatNet version (None until detected)."""
    return self._version

  def _version_text(self) -> str:
    if self._version is None:
      return '(version not yet detected)'
    return f'{self._version[0]}.{self._version[1]}'

  @property
  def stats(self) -> dict[str, int]:
    """Counts of frames decoded, malformed datagrams, other messages, and
    untracked bodies dropped."""
    with self._lock:
      return dict(self._stats)

  def status(self) -> str:
    """A one-line summary for error messages."""
    host, port = self.address
    mode = (
      f'multicast {self._multicast}'
      if self._multicast is not None
      else 'unicast'
    )
    stats = self.stats
    text = (
      f'NatNet {self._version_text()} {mode} on port {port}: '
      f'{stats["frames"]} frames, {stats["malformed"]} malformed, '
      f'{stats["invalid"]} untracked bodies'
    )
    if self._last_error:
      text += f' (last error: {self._last_error})'
    return text

  def poll(self) -> dict[str, tracking.Pose]:
    """The latest pose of each body received since the previous poll."""
    with self._lock:
      poses = {str(i): self._latest[i] for i in sorted(self._new)}
      self._new.clear()
    return poses

  def latest(self) -> dict[str, tracking.Pose]:
    """The latest pose of every body ever received."""
    with self._lock:
      return {str(i): pose for i, pose in self._latest.items()}

  def close(self) -> None:
    """Stops the receiver thread and closes the socket (idempotent)."""
    if self._stop.is_set():
      return
    self._stop.set()
    self._thread.join(timeout=1.0)
    self._socket.close()

  def __enter__(self) -> 'NatNetClient':
    return self

  def __exit__(self, *exc_info) -> None:
    self.close()

  def _send(self, datagram: bytes) -> None:
    try:
      self._socket.sendto(datagram, self._server)
    except OSError as error:  # Unreachable server: retried at keep-alive.
      logging.debug('NatNet request to %s failed: %s', self._server, error)

  def _run(self) -> None:
    sock = self._socket
    while not self._stop.is_set():
      if self._next_keepalive and time.monotonic() >= self._next_keepalive:
        self._send(encode_request(NAT_KEEPALIVE))
        self._next_keepalive = time.monotonic() + _KEEPALIVE_INTERVAL
      try:
        readable, _, _ = select.select([sock], [], [], _SELECT_TIMEOUT)
      except (OSError, ValueError):  # Closed under us.
        return
      if not readable:
        continue
      while True:  # Drain: only the newest pose of each body is kept.
        try:
          datagram, sender = sock.recvfrom(_MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
          break
        except OSError:
          return
        self._receive(datagram, sender)

  def _receive(self, datagram: bytes, sender) -> None:
    now = self._clock()
    if self._server is not None and sender[0] != self._server[0]:
      return
    try:
      if self._version is None and datagram[:2] == bytes([NAT_FRAMEOFDATA, 0]):
        self._version = detect_version(datagram[_HEADER.size :])
        logging.info('NatNet: the stream is version %s', self._version)
      frame = decode_message(datagram, self._version or DEFAULT_VERSION)
    except NatNetError as error:
      with self._lock:
        self._stats['malformed'] += 1
        self._last_error = str(error)
      if now - self._last_error_log > _ERROR_LOG_INTERVAL:
        self._last_error_log = now
        logging.warning('NatNet: malformed datagram from %s: %s', sender, error)
      return
    with self._lock:
      if frame is None:
        self._stats['other'] += 1
        return
      self._stats['frames'] += 1
      for body in frame.rigid_bodies:
        if not body.tracking_valid:
          self._stats['invalid'] += 1
          continue
        self._latest[body.id] = tracking.Pose(
          position=np.array(body.position, dtype=float),
          quaternion=np.array(body.quaternion, dtype=float),
          timestamp=now,
        )
        self._new.add(body.id)
