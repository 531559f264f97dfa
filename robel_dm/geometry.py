"""Angles, rotations and small vectors, shared by tasks and hardware.

Quaternions are (w, x, y, z), as in MuJoCo. Euler angles are ROBEL's
rotating-frame x-y-z angles (a, b, c) of R = Rx(a) Ry(b) Rz(c)
(transforms3d's 'rxyz').
"""

import math

import numpy as np

# Below this |cos(pitch)| the Euler rates are undefined (gimbal lock); the
# rates are computed with the cosine clamped to it.
_MIN_COS_PITCH = 1e-6
# Below this horizontal length of a body's forward axis its heading is
# taken from its x-axis instead (the body points up or down).
_MIN_HEADING_NORM = 1e-3


# --- Angles and vectors -----------------------------------------------------


def wrap_angle(angle):
  """Wraps radians to [-pi, pi)."""
  return (angle + np.pi) % (2 * np.pi) - np.pi


def dot(a: np.ndarray, b: np.ndarray) -> float:
  """Inner product of two small vectors, the same on every CPU.

  numpy's own summation in a fixed order, not BLAS (np.dot and
  np.linalg.norm): OpenBLAS picks its kernel by CPU, and kernels round
  differently, so rewards would differ in the last bit between machines.
  """
  return float(np.add.reduce(np.multiply(a, b)))


def norm(vector: np.ndarray) -> float:
  """Euclidean norm of a small vector (see `dot`)."""
  return math.sqrt(dot(vector, vector))


def cosine(a: np.ndarray, b: np.ndarray) -> float:
  """Cosine of the angle between two vectors (0 if either is zero)."""
  denominator = math.sqrt(dot(a, a) * dot(b, b))
  return dot(a, b) / denominator if denominator > 0 else 0.0


# --- Euler angles -----------------------------------------------------------


def euler_xyz(rotation) -> tuple[float, float, float]:
  """Rotating-frame x-y-z Euler angles (a, b, c) of R = Rx(a) Ry(b) Rz(c).

  Args:
    rotation: a 3x3 rotation matrix (nested sequences or an array).
  """
  (r00, r01, r02), (_, _, r12), (_, _, r22) = rotation
  pitch = math.atan2(r02, math.hypot(r00, r01))
  return math.atan2(-r12, r22), pitch, math.atan2(-r01, r00)


def euler_xyz_rates(euler, angular_velocity_world) -> tuple[float, ...]:
  """Rates of rotating x-y-z Euler angles for a world angular velocity.

  With R = Rx(a) Ry(b) Rz(c): w = (1,0,0) da + Rx(a) (0,1,0) db
  + Rx(a) Ry(b) (0,0,1) dc, solved for (da, db, dc).
  """
  roll, pitch, _ = euler
  wx, wy, wz = angular_velocity_world
  sin_roll, cos_roll = math.sin(roll), math.cos(roll)
  cos_pitch = math.cos(pitch)
  if abs(cos_pitch) < _MIN_COS_PITCH:
    cos_pitch = math.copysign(_MIN_COS_PITCH, cos_pitch)
  yaw_rate = (cos_roll * wz - sin_roll * wy) / cos_pitch
  pitch_rate = cos_roll * wy + sin_roll * wz
  roll_rate = wx - math.sin(pitch) * yaw_rate
  return roll_rate, pitch_rate, yaw_rate


# --- Quaternions ------------------------------------------------------------


def yaw_quaternion(yaw: float) -> np.ndarray:
  """The rotation by `yaw` rad about z."""
  return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def upright(quaternion) -> float:
  """Uprightness of an orientation: the cosine between the body's z-axis
  and world z (R[2, 2] of its rotation matrix)."""
  _, x, y, _ = quaternion
  return 1.0 - 2.0 * (x * x + y * y)


def quat_multiply(a, b) -> np.ndarray:
  """The Hamilton product a b (rotation b, then a)."""
  aw, ax, ay, az = a
  bw, bx, by, bz = b
  return np.array(
    [
      aw * bw - ax * bx - ay * by - az * bz,
      aw * bx + ax * bw + ay * bz - az * by,
      aw * by - ax * bz + ay * bw + az * bx,
      aw * bz + ax * by - ay * bx + az * bw,
    ]
  )


def quat_conjugate(q) -> np.ndarray:
  return np.array([q[0], -q[1], -q[2], -q[3]], dtype=float)


def quat_normalize(q) -> np.ndarray:
  """The unit quaternion of q.

  Raises:
    ValueError: if q is not finite or (nearly) zero.
  """
  q = np.asarray(q, dtype=float)
  length = norm(q)
  if not np.isfinite(length) or length < 1e-9:
    raise ValueError(f'not a rotation quaternion: {q}')
  return q / length


def quat_to_matrix(q) -> np.ndarray:
  """The rotation matrix of a unit quaternion."""
  w, x, y, z = quat_normalize(q)
  return np.array(
    [
      [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
  )


def matrix_to_quat(matrix) -> np.ndarray:
  """The unit quaternion (w >= 0) of a rotation matrix.

  Raises:
    ValueError: if `matrix` is not a proper rotation (orthonormal, det +1).
  """
  m = np.asarray(matrix, dtype=float)
  if (
    m.shape != (3, 3)
    or not np.allclose(m @ m.T, np.eye(3), atol=1e-6)
    or np.linalg.det(m) < 0
  ):
    raise ValueError(f'not a proper rotation matrix:\n{m}')
  # The largest of 4 w^2, 4 x^2, 4 y^2, 4 z^2 gives a well-conditioned
  # division (Shepperd's method).
  trace = np.trace(m)
  k = int(np.argmax([trace, m[0, 0], m[1, 1], m[2, 2]]))
  if k == 0:
    s = 2.0 * math.sqrt(1.0 + trace)
    q = [
      s / 4,
      (m[2, 1] - m[1, 2]) / s,
      (m[0, 2] - m[2, 0]) / s,
      (m[1, 0] - m[0, 1]) / s,
    ]
  elif k == 1:
    s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
    q = [
      (m[2, 1] - m[1, 2]) / s,
      s / 4,
      (m[0, 1] + m[1, 0]) / s,
      (m[0, 2] + m[2, 0]) / s,
    ]
  elif k == 2:
    s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
    q = [
      (m[0, 2] - m[2, 0]) / s,
      (m[0, 1] + m[1, 0]) / s,
      s / 4,
      (m[1, 2] + m[2, 1]) / s,
    ]
  else:
    s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
    q = [
      (m[1, 0] - m[0, 1]) / s,
      (m[0, 2] + m[2, 0]) / s,
      (m[1, 2] + m[2, 1]) / s,
      s / 4,
    ]
  q = quat_normalize(q)
  return -q if q[0] < 0 else q


def quat_from_rotation_vector(vector) -> np.ndarray:
  """exp: the rotation by |vector| rad about vector's direction."""
  vector = np.asarray(vector, dtype=float)
  angle = norm(vector)
  if angle < 1e-12:
    return np.array([1.0, *(vector / 2)])
  axis = vector / angle
  return np.array([math.cos(angle / 2), *(math.sin(angle / 2) * axis)])


def quat_to_rotation_vector(q) -> np.ndarray:
  """log: the rotation vector (axis x angle, angle in [0, pi]) of q."""
  q = quat_normalize(q)
  if q[0] < 0:  # The same rotation; this sign gives the shorter way.
    q = -q
  sine = norm(q[1:])
  if sine < 1e-12:
    return 2.0 * q[1:]
  return 2.0 * math.atan2(sine, q[0]) * q[1:] / sine


def heading(q) -> float:
  """The yaw of an orientation: the angle about z from +y to the body's
  forward (y) axis projected on the floor (its x-axis if y is vertical)."""
  m = quat_to_matrix(q)
  forward = m[:, 1]
  if math.hypot(forward[0], forward[1]) > _MIN_HEADING_NORM:
    return math.atan2(-forward[0], forward[1])
  return math.atan2(m[1, 0], m[0, 0])


def average_quaternions(quaternions, weights=None) -> np.ndarray:
  """Markley's average of unit quaternions.

  The average is the unit quaternion q maximizing sum_i w_i (q_i . q)^2,
  i.e. the eigenvector of M = sum_i w_i q_i q_i^T with the largest
  eigenvalue (F. L. Markley, Y. Cheng, J. L. Crassidis, Y. Oshman,
  "Averaging Quaternions", J. Guidance, Control, and Dynamics 30(4), 2007).
  It minimizes the weighted sum of squared Frobenius distances between the
  rotation matrices, and is insensitive to each q_i's sign (q and -q are
  the same rotation), unlike a component-wise mean.

  Args:
    quaternions: (N, 4) quaternions (w, x, y, z); need not be unit.
    weights: (N,) non-negative weights; equal by default.

  Returns:
    The average (w >= 0).
  """
  q = np.array([quat_normalize(x) for x in quaternions])
  w = np.ones(len(q)) if weights is None else np.asarray(weights, float)
  m = (q * w[:, None]).T @ q
  _, vectors = np.linalg.eigh(m)  # Eigenvalues ascending.
  mean = vectors[:, -1]
  return -mean if mean[0] < 0 else mean
