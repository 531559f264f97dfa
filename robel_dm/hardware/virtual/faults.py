"""Communication faults to inject into a virtual bus, at runtime.

Absent servos (as if unplugged), servos that ignore their next packets,
servos whose next group writes (sync or bulk) are lost on the way, status
packets with a broken CRC, and the silence of the rest of the chain
after a silent servo in a sync/bulk read (docs/dynamixel.md section 1.7).
`bus.Bus` consults a `Faults` for every packet.
"""

from collections.abc import Iterable, Mapping
import threading


class Faults:
  """Communication faults, changeable at runtime from any thread.

  Mutate the attributes through the methods (or while holding `lock`).

  Attributes:
    absent: IDs that never answer (as if unplugged).
    mute: ID -> how many of the next packets addressed to that servo it
      ignores (neither executed nor answered: a timeout).
    corrupt_crc: ID -> how many of its next status packets carry a wrong CRC
      (for a fast read: its block's CRC).
    lost_writes: ID -> how many of the next group writes (sync or bulk;
      they have no reply) lose that servo's data on the way.
    chain_break: in a sync/bulk read, servos after a silent one stay silent
      too, as on a real bus (docs/dynamixel.md section 1.7).
    lock: guards the attributes.
  """

  def __init__(
    self,
    absent: Iterable[int] = (),
    mute: Mapping[int, int] | None = None,
    corrupt_crc: Mapping[int, int] | None = None,
    chain_break: bool = True,
  ):
    self.lock = threading.Lock()
    self.absent = set(absent)
    self.mute = dict(mute or {})
    self.corrupt_crc = dict(corrupt_crc or {})
    self.lost_writes: dict[int, int] = {}
    self.chain_break = chain_break

  def set_absent(self, motor_id: int, absent: bool = True) -> None:
    with self.lock:
      if absent:
        self.absent.add(motor_id)
      else:
        self.absent.discard(motor_id)

  def mute_next(self, motor_id: int, count: int = 1) -> None:
    """Makes the servo ignore its next `count` packets."""
    with self.lock:
      self.mute[motor_id] = self.mute.get(motor_id, 0) + count

  def corrupt_next(self, motor_id: int, count: int = 1) -> None:
    """Breaks the CRC of the servo's next `count` status packets."""
    with self.lock:
      self.corrupt_crc[motor_id] = self.corrupt_crc.get(motor_id, 0) + count

  def lose_next_write(self, motor_id: int, count: int = 1) -> None:
    """Loses the servo's data in the next `count` group writes."""
    with self.lock:
      self.lost_writes[motor_id] = self.lost_writes.get(motor_id, 0) + count

  def clear(self) -> None:
    """Removes every fault (chain_break stays)."""
    with self.lock:
      self.absent.clear()
      self.mute.clear()
      self.corrupt_crc.clear()
      self.lost_writes.clear()

  def is_absent(self, motor_id: int) -> bool:
    if not self.absent:  # Fast path, safe under the GIL.
      return False
    with self.lock:
      return motor_id in self.absent

  def take_mute(self, motor_id: int) -> bool:
    """Whether the servo ignores this packet (uses up one count)."""
    return self._take(self.mute, motor_id)

  def take_lost_write(self, motor_id: int) -> bool:
    """Whether this group write's data for the servo is lost (uses up one
    count)."""
    return self._take(self.lost_writes, motor_id)

  def take_corrupt(self, motor_id: int) -> bool:
    """Whether this status packet gets a wrong CRC (uses up one count)."""
    return self._take(self.corrupt_crc, motor_id)

  def _take(self, counts: dict[int, int], motor_id: int) -> bool:
    if not counts:  # Fast path, safe under the GIL.
      return False
    with self.lock:
      count = counts.get(motor_id, 0)
      if count <= 0:
        return False
      if count == 1:
        del counts[motor_id]
      else:
        counts[motor_id] = count - 1
      return True
