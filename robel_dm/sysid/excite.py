"""Excitation sequences: joint targets that reveal a servo's dynamics.

Two signals, both around the robot's excitation pose (see
`robel_dm.tasks.excitation`) and inside its action range:

  steps: each joint holds a random level for a random 0.2-0.6 s, then jumps
    to the next (step responses at many amplitudes and directions, with
    gravity loading the joints differently at each level);
  chirp: each joint follows a sine whose frequency sweeps from 0.2 to 3 Hz,
    the joints out of phase.

Every target change still passes ROBEL's velocity clamp on the way to the
motors; the recording keeps the targets actually sent.
"""

import dataclasses
from typing import Any

import dm_env
import numpy as np

from robel_dm import numeric

SIGNALS = ('steps', 'chirp')
# Hold time of one level of the steps signal, s.
STEP_HOLD = (0.2, 0.6)
# Frequency sweep of the chirp signal, Hz.
CHIRP_FREQUENCY = (0.2, 3.0)
# Targets keep this far inside the action range, rad.
RANGE_MARGIN = 0.02


@dataclasses.dataclass(frozen=True)
class Excitation:
  """What an excitation episode drives.

  Attributes:
    signal: one of `SIGNALS`.
    duration: seconds.
    amplitude: fraction of each joint's half action range the targets move
      away from the excitation pose (0..1].
    joints: names of the joints to excite (the others hold the pose); None
      for all.
    seed: seed of the random levels and hold times.
  """

  signal: str = 'steps'
  duration: float = 10.0
  amplitude: float = 0.4
  joints: tuple[str, ...] | None = None
  seed: int = 0

  def __post_init__(self):
    if self.signal not in SIGNALS:
      raise ValueError(f'signal must be one of {SIGNALS}, got {self.signal!r}')
    if not (numeric.is_finite(self.duration) and self.duration > 0):
      raise ValueError(f'duration must be positive, got {self.duration!r} s')
    if not 0 < self.amplitude <= 1:
      raise ValueError(f'amplitude must be in (0, 1], got {self.amplitude!r}')

  def to_dict(self) -> dict[str, Any]:
    data = dataclasses.asdict(self)
    data['joints'] = None if self.joints is None else list(self.joints)
    return data


def targets(
  excitation: Excitation,
  joint_names: tuple[str, ...],
  center: np.ndarray,
  low: np.ndarray,
  high: np.ndarray,
  control_timestep: float,
) -> np.ndarray:
  """The joint targets of every control step, (steps, joints), rad.

  Raises:
    ValueError: for a joint name the robot does not have.
  """
  check_joints(excitation, joint_names)
  chosen = joint_names if excitation.joints is None else excitation.joints
  mask = np.array([name in chosen for name in joint_names])
  half_range = (high - low) / 2
  amplitude = excitation.amplitude * half_range
  _check_room(
    excitation.amplitude, amplitude, mask, joint_names, center, low, high
  )
  steps = max(1, round(excitation.duration / control_timestep))
  time = np.arange(1, steps + 1) * control_timestep
  rng = np.random.default_rng(excitation.seed)
  if excitation.signal == 'steps':
    offsets = np.zeros((steps, len(joint_names)))
    for j in range(len(joint_names)):
      start = 0
      while start < steps:
        hold = rng.uniform(*STEP_HOLD)
        stop = min(steps, start + max(1, round(hold / control_timestep)))
        offsets[start:stop, j] = rng.uniform(-1, 1) * amplitude[j]
        start = stop
  else:
    low_f, high_f = CHIRP_FREQUENCY
    # Phase of a linear sweep from low_f to high_f over the duration.
    sweep = (high_f - low_f) / excitation.duration
    phase = 2 * np.pi * (low_f * time + sweep * time**2 / 2)
    shifts = 2 * np.pi * np.arange(len(joint_names)) / len(joint_names)
    offsets = np.sin(phase[:, None] + shifts[None, :]) * amplitude
  offsets[:, ~mask] = 0.0
  return center + offsets


def check_joints(excitation: Excitation, joint_names: tuple[str, ...]) -> None:
  """Raises ValueError naming the joints to excite that the robot (its
  `joint_names`) does not have."""
  unknown = sorted(set(excitation.joints or ()) - set(joint_names))
  if unknown:
    raise ValueError(f'unknown joints {unknown}; the robot has {joint_names}')


def _check_room(fraction, amplitude, mask, joint_names, center, low, high):
  """Raises ValueError if a chosen joint's targets would come within
  RANGE_MARGIN of its action range's end (they would have to be clipped,
  flattening the excitation)."""
  room = np.minimum(center - low, high - center) - RANGE_MARGIN
  too_far = mask & (amplitude > room)
  if too_far.any():
    fits = np.min(room[mask] / ((high - low)[mask] / 2))
    raise ValueError(
      f'amplitude {fraction} takes {joint_names[int(np.argmax(too_far))]} '
      f'beyond its action range (less {RANGE_MARGIN} rad) from the pose; at '
      f'most {np.floor(fits * 100) / 100:.2f} fits the joints excited'
    )


def run(
  env: dm_env.Environment, excitation: Excitation, episodes: int = 1
) -> int:
  """Drives `env` (a `suite.load_excitation` environment, usually wrapped
  in a `recording.Recorder`) through the excitation.

  Each episode uses seed `excitation.seed + episode`.

  Returns:
    The number of control steps run.
  """
  task = env.task
  names = tuple(joint.name for joint in task.robot.joints)
  low, high = task.action_range(env.physics)
  # Every sequence first, so that a bad excitation fails before anything
  # moves.
  sequences = [
    targets(
      dataclasses.replace(excitation, seed=excitation.seed + episode),
      names,
      task.center_pose,
      low,
      high,
      task.control_timestep,
    )
    for episode in range(episodes)
  ]
  count = 0
  for sequence in sequences:
    env.reset()
    for target in sequence:
      timestep = env.step(task.normalize_joint_targets(target))
      count += 1
      if timestep.last():
        break
  return count
