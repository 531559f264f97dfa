"""Motion-tracker poses turned into the D'Kitty's torso state.

A D'Kitty on real motors needs its torso pose (uprightness, heading,
position) from a motion tracker (docs/robel_reference.md section 4.6). This
module holds the tracker-independent part:

  * `Pose` and the `TrackerSource` protocol: anything whose `poll()` returns
    the latest pose per rigid body (OptiTrack NatNet: `natnet.NatNetClient`;
    tests and simulations: `SimulatedSource`).
  * `TorsoTracker`: maps a source's poses into robel_dm's world and torso
    frames, calibrates the origin at reset, estimates the velocities the
    trackers do not measure, and gives `torso_state()`, the callable
    `hardware.environment.make_environment(torso_source=...)` expects.

Frames. A raw pose is the tracked body's pose in the tracker's world frame.
`TorsoTracker` applies, in order (1 and 2 are its `Frames`):
  1. `frame_rotation` R_f, a fixed rotation from the tracker's world frame
     to a z-up frame (`Y_UP_TO_Z_UP` for a y-up tracker such as Motive's
     default or OpenVR). ROBEL 0.1.2 declared this matrix for OpenVR but
     never applied it (docs/robel_reference.md sections 4.6, 7); here it is
     applied.
  2. `body_rotation` / `body_offset`: where the torso frame is relative to
     the tracked body (the tracker's mounting): the torso's orientation and
     origin expressed in the tracked body's frame.
  3. The origin calibration (`calibrate_origin`): a rotation about z and a
     translation, chosen at reset so that the torso is at robel_dm's frame
     origin (0, 0, 0.3) facing +y (yaw 0), as ROBEL did. Tilt is kept:
     a rotation about world z leaves the torso's uprightness unchanged.

All quaternions are (w, x, y, z), as in MuJoCo; their arithmetic is in
`robel_dm.geometry`.
"""

from collections.abc import Callable, Mapping
import dataclasses
import logging
import time
from typing import Protocol

import numpy as np

from robel_dm import geometry
from robel_dm.entities import dkitty

# Maps a y-up tracker frame (x, y up, z) to robel_dm's z-up world: the
# tracker's +y becomes +z and its +z becomes -y (a proper rotation, det +1).
# The matrix ROBEL 0.1.2 declared for OpenVR.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# Where `calibrate_origin` puts the torso: robel_dm's (and ROBEL's) D'Kitty
# frame origin, m.
ORIGIN = dkitty.ROBEL_FRAME_ORIGIN

DEFAULT_STALE_TIMEOUT = 0.5  # s
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


class TrackingError(RuntimeError):
  """No usable pose: nothing received, or the latest is too old."""


@dataclasses.dataclass(frozen=True, eq=False)
class Pose:
  """A rigid body's pose in a tracker's world frame.

  Attributes:
    position: (x, y, z), m.
    quaternion: orientation (w, x, y, z), body to world.
    timestamp: when it was measured or received, s (any monotonic origin,
      the same as the consuming `TorsoTracker`'s clock).
  """

  position: np.ndarray
  quaternion: np.ndarray
  timestamp: float

  def __post_init__(self):
    position = np.array(self.position, dtype=float).reshape(3)
    quaternion = np.array(self.quaternion, dtype=float).reshape(4)
    object.__setattr__(self, 'position', position)
    object.__setattr__(self, 'quaternion', quaternion)
    object.__setattr__(self, 'timestamp', float(self.timestamp))


class TrackerSource(Protocol):
  """Where poses come from (a motion-capture client, a simulation)."""

  def poll(self) -> dict[str, Pose]:
    """The latest pose per rigid body (name or ID as a string) received
    since the previous poll; empty when nothing new arrived."""

  def close(self) -> None:
    """Releases the source (sockets, threads)."""


# --- Rotations ---------------------------------------------------------------


def _as_quaternion(rotation) -> np.ndarray:
  """A rotation given as a 3x3 matrix or a (w, x, y, z) quaternion."""
  rotation = np.asarray(rotation, dtype=float)
  if rotation.shape == (3, 3):
    return geometry.matrix_to_quat(rotation)
  if rotation.shape == (4,):
    return geometry.quat_normalize(rotation)
  raise ValueError(
    f'a rotation is a 3x3 matrix or a quaternion, not shape {rotation.shape}'
  )


# --- Sources -----------------------------------------------------------------


class SimulatedSource:
  """A `TrackerSource` whose poses come from a callable.

  Each poll calls `poses()` once: it returns name -> `Pose` (or an empty
  mapping when nothing is visible). For tests, and for feeding a simulated
  robot's torso through the same code path as a real tracker.
  """

  def __init__(
    self,
    poses: Callable[[], Mapping[str | int, Pose]],
    on_close: Callable[[], None] | None = None,
  ):
    """Initializes the source.

    Args:
      poses: returns the current pose of each visible body.
      on_close: called once by `close`.
    """
    self._poses = poses
    self._on_close = on_close
    self._closed = False
    self.polls = 0

  def poll(self) -> dict[str, Pose]:
    if self._closed:
      raise TrackingError('the simulated tracker source is closed')
    self.polls += 1
    return {str(name): pose for name, pose in self._poses().items()}

  def close(self) -> None:
    if not self._closed:
      self._closed = True
      if self._on_close is not None:
        self._on_close()

  def status(self) -> str:
    return f'simulated source, {self.polls} polls'


# --- The torso tracker -------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Frames:
  """Where the torso frame is, relative to the tracker's frames.

  Steps 1 and 2 of the module docstring: the tracker's world frame, and
  the tracker's mounting on the torso. Rotations are 3x3 matrices or
  (w, x, y, z) quaternions; each is checked and copied when given.

  Attributes:
    frame_rotation: rotation from the tracker's world frame to a z-up
      frame; None if the tracker is z-up already. `Y_UP_TO_Z_UP` for a
      y-up tracker.
    body_rotation: the torso frame's orientation in the tracked body's
      frame; identity if None.
    body_offset: the torso origin in the tracked body's frame, m; zero if
      None.
  """

  frame_rotation: np.ndarray | None = None
  body_rotation: np.ndarray | None = None
  body_offset: np.ndarray | None = None

  def __post_init__(self):
    for name in ('frame_rotation', 'body_rotation'):
      rotation = getattr(self, name)
      if rotation is not None:
        _as_quaternion(rotation)  # Raises for a wrong shape.
        object.__setattr__(self, name, np.array(rotation, dtype=float))
    if self.body_offset is not None:
      offset = np.array(self.body_offset, dtype=float)
      object.__setattr__(self, 'body_offset', offset)

  def frame_quaternion(self) -> np.ndarray:
    """`frame_rotation` as a quaternion (identity if None)."""
    return _quaternion_or_identity(self.frame_rotation)

  def body_quaternion(self) -> np.ndarray:
    """`body_rotation` as a quaternion (identity if None)."""
    return _quaternion_or_identity(self.body_rotation)

  def offset(self) -> np.ndarray:
    """`body_offset`, m (zero if None)."""
    return np.zeros(3) if self.body_offset is None else self.body_offset.copy()


def _quaternion_or_identity(rotation: np.ndarray | None) -> np.ndarray:
  return _IDENTITY.copy() if rotation is None else _as_quaternion(rotation)


@dataclasses.dataclass(frozen=True)
class Calibration:
  """What `calibrate_origin` measured.

  Attributes:
    position: the torso's mean position before calibration (z-up tracker
      frame), m.
    yaw: the heading removed, rad.
    samples: how many poses were averaged.
    spread: the largest distance of a sample from the mean, m (large if the
      robot moved during calibration).
  """

  position: np.ndarray
  yaw: float
  samples: int
  spread: float


class TorsoTracker:
  """The D'Kitty's torso (and targets) from a tracker source.

  Velocities. Trackers report poses only, so velocities are estimated by
  finite differences of consecutive torso samples (t0, p0, q0), (t1, p1,
  q1) with dt = t1 - t0 > 0:
    linear (world):   v = (p1 - p0) / dt;
    angular (torso):  w = log(conj(q0) q1) / dt, the rotation vector of the
                      relative rotation, taken the short way.
  Both are exact for constant velocities (constant torso-frame angular
  velocity), and are the mean over the interval otherwise (an error of
  about |acceleration| dt / 2 against the velocity at t1). An optional
  first-order low-pass (time constant `velocity_time_constant`) smooths
  them: x <- x + dt / (tau + dt) (x_new - x). Samples with dt = 0 (the same
  measurement twice) keep the current estimate; dt < 0 (a source restart)
  or a gap longer than `stale_timeout` restart it from zero.
  """

  def __init__(
    self,
    source: TrackerSource,
    body: str | int,
    target_body: str | int | None = None,
    heading_body: str | int | None = None,
    *,
    frames: Frames | None = None,
    stale_timeout: float = DEFAULT_STALE_TIMEOUT,
    velocity_time_constant: float = 0.0,
    clock: Callable[[], float] = time.monotonic,
  ):
    """Initializes the tracker.

    Args:
      source: where poses come from; closed by `close`.
      body: the torso's rigid body (name or ID) in the source.
      target_body: the Orient/Walk target's body, if tracked.
      heading_body: the Walk heading marker's body; the target by default
        (as in ROBEL).
      frames: the tracker's world frame and its mounting on the torso;
        None for a z-up tracker whose body frame is the torso's. For a
        y-up tracker: `Frames(frame_rotation=Y_UP_TO_Z_UP)`.
      stale_timeout: `torso_state` fails when the newest torso pose is
        older than this, s.
      velocity_time_constant: low-pass time constant of the velocity
        estimates, s (0: none).
      clock: the time base of the source's timestamps, s.
    """
    if stale_timeout <= 0:
      raise ValueError(f'stale_timeout must be positive: {stale_timeout}')
    if velocity_time_constant < 0:
      raise ValueError(
        f'velocity_time_constant must be >= 0: {velocity_time_constant}'
      )
    self._source = source
    self.body = str(body)
    self.target_body = None if target_body is None else str(target_body)
    if heading_body is None:
      heading_body = self.target_body
    self.heading_body = None if heading_body is None else str(heading_body)
    frames = Frames() if frames is None else frames
    self.frames = frames
    self._frame_q = frames.frame_quaternion()
    self._body_q = frames.body_quaternion()
    self._body_offset = frames.offset()
    self._stale_timeout = float(stale_timeout)
    self._tau = float(velocity_time_constant)
    self._clock = clock
    self._latest: dict[str, Pose] = {}
    # The torso in the z-up tracker frame ("level frame"): time, position,
    # orientation, and the velocity estimates.
    self._time: float | None = None
    self._position = np.zeros(3)
    self._quaternion = _IDENTITY.copy()
    self._velocity = np.zeros(3)  # Level frame.
    self._angular_velocity = np.zeros(3)  # Torso frame.
    # Level frame -> robel_dm world (set by `calibrate_origin`).
    self._world_q = _IDENTITY.copy()
    self._world_m = np.eye(3)
    self._world_t = np.zeros(3)
    self.calibration: Calibration | None = None

  # --- Polling ---------------------------------------------------------------

  def update(self) -> bool:
    """Polls the source once and folds in what it returned.

    Returns:
      Whether a new torso pose arrived.
    """
    poses = self._source.poll()
    for name, pose in poses.items():
      self._latest[name] = pose
    torso = poses.get(self.body)
    if torso is not None:
      self._add_torso_sample(torso)
    return torso is not None

  def _level_pose(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """The torso pose in the z-up tracker frame from a raw body pose."""
    tracked_q = geometry.quat_multiply(
      self._frame_q, geometry.quat_normalize(pose.quaternion)
    )
    position = geometry.quat_to_matrix(self._frame_q) @ pose.position
    position = position + geometry.quat_to_matrix(tracked_q) @ self._body_offset
    return position, geometry.quat_normalize(
      geometry.quat_multiply(tracked_q, self._body_q)
    )

  def _add_torso_sample(self, pose: Pose) -> None:
    position, quaternion = self._level_pose(pose)
    t = pose.timestamp
    if self._time is None:
      self._velocity[:] = 0.0
      self._angular_velocity[:] = 0.0
    else:
      dt = t - self._time
      # Keep the quaternion in the previous one's hemisphere (the same
      # rotation) so that the reported quaternion does not flip sign.
      if np.dot(quaternion, self._quaternion) < 0:
        quaternion = -quaternion
      if dt < 0 or dt > self._stale_timeout:
        self._velocity[:] = 0.0
        self._angular_velocity[:] = 0.0
      elif dt > 0:
        velocity = (position - self._position) / dt
        relative = geometry.quat_multiply(
          geometry.quat_conjugate(self._quaternion), quaternion
        )
        angular_velocity = geometry.quat_to_rotation_vector(relative) / dt
        gain = dt / (self._tau + dt)
        self._velocity += gain * (velocity - self._velocity)
        self._angular_velocity += gain * (
          angular_velocity - self._angular_velocity
        )
    self._time = t
    self._position = position
    self._quaternion = quaternion

  # --- Torso -----------------------------------------------------------------

  def torso_state(self):
    """The torso's state in robel_dm's world, for `make_environment`.

    Polls the source first.

    Returns:
      (position (3,) m, quaternion (4,) w x y z, linear velocity (3,) m/s in
      the world frame, angular velocity (3,) rad/s in the torso frame): the
      free joint's qpos and qvel.

    Raises:
      TrackingError: if no torso pose was ever received, or the newest is
        older than `stale_timeout`.
    """
    self.update()
    if self._time is None:
      raise TrackingError(
        f'no pose received for the torso body {self.body!r} yet '
        f'({self._describe_source()}); is the tracker streaming it and '
        'the body visible?'
      )
    age = self._clock() - self._time
    if age > self._stale_timeout:
      raise TrackingError(
        f'the torso body {self.body!r} was last seen {age:.2f} s ago '
        f'(stale after {self._stale_timeout} s; {self._describe_source()}); '
        'is it occluded or the tracker stopped?'
      )
    return (
      self._world_m @ self._position + self._world_t,
      geometry.quat_multiply(self._world_q, self._quaternion),
      self._world_m @ self._velocity,
      self._angular_velocity.copy(),
    )

  def calibrate_origin(
    self,
    samples: int = 10,
    timeout: float = 2.0,
    poll_interval: float = 0.01,
  ) -> Calibration:
    """Makes the torso's current pose robel_dm's origin, facing +y.

    Averages `samples` new torso poses (positions: arithmetic mean;
    orientations: `average_quaternions`), then sets the world transform so
    that the mean torso position is `ORIGIN` (0, 0, 0.3) and its heading is
    0, removing the yaw only (tilt is kept). As ROBEL does at each reset
    (docs/robel_reference.md section 4.6). Targets are mapped by the same
    transform.

    Args:
      samples: how many new torso poses to average.
      timeout: wall-clock seconds to wait for them.
      poll_interval: wait between polls that bring nothing new, s.

    Returns:
      What was measured.

    Raises:
      TrackingError: if fewer than `samples` poses arrive in time.
    """
    if samples < 1:
      raise ValueError(f'samples must be >= 1: {samples}')
    positions, quaternions = [], []
    deadline = time.monotonic() + timeout
    while len(positions) < samples:
      if self.update():
        positions.append(self._position.copy())
        quaternions.append(self._quaternion.copy())
        continue
      if time.monotonic() >= deadline:
        raise TrackingError(
          f'origin calibration: {len(positions)} of {samples} poses of the '
          f'torso body {self.body!r} arrived in {timeout} s '
          f'({self._describe_source()})'
        )
      time.sleep(poll_interval)
    positions = np.array(positions)
    mean_position = positions.mean(axis=0)
    yaw = geometry.heading(geometry.average_quaternions(quaternions))
    self._world_q = geometry.yaw_quaternion(-yaw)
    self._world_m = geometry.quat_to_matrix(self._world_q)
    self._world_t = ORIGIN - self._world_m @ mean_position
    spread = float(np.max(np.linalg.norm(positions - mean_position, axis=1)))
    if spread > 0.01:
      logging.warning(
        'torso moved %.3f m during origin calibration of body %r',
        spread,
        self.body,
      )
    self.calibration = Calibration(mean_position, yaw, samples, spread)
    return self.calibration

  def reset_origin(self) -> None:
    """Forgets the calibration (world = z-up tracker frame)."""
    self._world_q = _IDENTITY.copy()
    self._world_m = np.eye(3)
    self._world_t = np.zeros(3)
    self.calibration = None

  # --- Targets ---------------------------------------------------------------

  def target_position(self) -> np.ndarray:
    """The target body's (x, y) in robel_dm's world, m.

    The latest pose ever received is used (as ROBEL reuses the cached
    pose of a target it loses); polls the source first.

    Raises:
      ValueError: if no target body is configured.
      TrackingError: if it was never seen.
    """
    return self._body_xy(self.target_body, 'target')

  def heading_position(self) -> np.ndarray:
    """The heading marker's (x, y) in robel_dm's world, m (the target's
    unless a heading body is configured). See `target_position`."""
    return self._body_xy(self.heading_body, 'heading')

  def _body_xy(self, name: str | None, role: str) -> np.ndarray:
    if name is None:
      raise ValueError(f'no {role} body is configured')
    self.update()
    pose = self._latest.get(name)
    if pose is None:
      raise TrackingError(
        f'no pose received for the {role} body {name!r} yet '
        f'({self._describe_source()})'
      )
    level = geometry.quat_to_matrix(self._frame_q) @ pose.position
    return (self._world_m @ level + self._world_t)[:2]

  # --- Misc ------------------------------------------------------------------

  def _describe_source(self) -> str:
    status = getattr(self._source, 'status', None)
    return status() if callable(status) else type(self._source).__name__

  def close(self) -> None:
    """Closes the source."""
    self._source.close()

  def __enter__(self) -> 'TorsoTracker':
    return self

  def __exit__(self, *exc_info) -> None:
    self.close()
