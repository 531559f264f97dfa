"""D'Kitty Walk on a robot with a tracked heading marker.

ROBEL's hardware Walk reads a second tracked body, a heading marker the
robot should face; simulation has none and faces the target itself. The
task takes the marker through `RobotIO.tracked_heading`.
"""

import math

import numpy as np
import pytest

from robel_dm import robot_io, suite


class _TrackedIO(robot_io.SimulatedRobotIO):
  """Simulation's robot IO, plus a heading marker at a fixed place."""

  def __init__(self, heading):
    self.heading = None if heading is None else np.asarray(heading, float)

  def tracked_heading(self):
    return self.heading


def _heading_after_reset(marker) -> float:
  env = suite.load('dkitty', 'walk_fixed', seed=0)
  env.task.use_robot_io(_TrackedIO(marker))
  timestep = env.reset()
  # The target is 2 m straight ahead (+y); the robot stands at the origin.
  np.testing.assert_allclose(env.task.target, [0.0, 2.0], atol=1e-12)
  return float(timestep.observation['heading'][0])


@pytest.mark.parametrize(
  'marker, expected',
  [
    (None, 1.0),  # No marker: face the target, straight ahead.
    ((1.0, 0.0), 0.0),  # A marker to the right: facing +y is 90 deg off.
    ((-1.0, -1.0), -math.sqrt(0.5)),  # Behind and to the left: 135 deg.
  ],
)
def test_walk_faces_the_tracked_heading_marker(marker, expected):
  assert _heading_after_reset(marker) == pytest.approx(expected, abs=0.02)
