"""A curriculum over the randomization (`set_randomization_scale`); the
agent that trains with it (`sac_curriculum`) is tested in
test_randomdynamics_agents.py.

Nominal values are the model's (ROBEL's D'Claw: damping 0.1, servo gain
2; D'Kitty: damping 1.0, gain 5); expected values are computed from them.
"""

import numpy as np
import pytest

from robel_dm import suite

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning')


def _physics_after_reset(domain, task, scale, seed=4):
  env = suite.load(domain, task, seed=seed)
  env.task.set_randomization_scale(scale)
  env.reset()
  return env


def test_scale_moves_each_draw_toward_the_nominal_robot():
  full, half, none = (
    _physics_after_reset('dclaw', 'pose_random_dynamics', scale)
    for scale in (1.0, 0.5, 0.0)
  )

  def servo(env):
    joints = env.physics.bind(env.task.robot.joints)
    actuators = env.physics.bind(env.task.robot.actuators)
    return np.concatenate(
      [joints.damping, joints.frictionloss, actuators.gainprm[:, 0]]
    )

  nominal = np.concatenate([np.full(9, 0.1), np.zeros(9), np.full(9, 2.0)])
  np.testing.assert_allclose(servo(none), nominal)
  np.testing.assert_allclose(servo(half), (servo(full) + nominal) / 2)
  assert not np.allclose(servo(full), nominal)
  # Biases follow the gains: a servo still pulls toward its target.
  actuators = half.physics.bind(half.task.robot.actuators)
  np.testing.assert_allclose(actuators.biasprm[:, 1], -actuators.gainprm[:, 0])


def test_scale_shrinks_the_dkitty_terrain_and_mass():
  full, half = (
    _physics_after_reset('dkitty', 'walk_random_dynamics', scale)
    for scale in (1.0, 0.5)
  )
  heights = full.task.arena.terrain_heights
  assert heights.max() > 0.04  # ROBEL's bumps reach 5 cm.
  np.testing.assert_allclose(half.task.arena.terrain_heights, heights / 2)
  nominal_mass = 1.834  # ROBEL's D'Kitty, kg.
  masses = [env.physics.model.body_mass.sum() for env in (full, half)]
  np.testing.assert_allclose(masses[1], (masses[0] + nominal_mass) / 2, 1e-3)


def test_scale_is_checked():
  env = suite.load('dclaw', 'pose_random_dynamics')
  with pytest.raises(ValueError, match=r'in \[0, 1\], got 1.5'):
    env.task.set_randomization_scale(1.5)
  with pytest.raises(ValueError, match='randomizes no physics'):
    suite.load('dclaw', 'pose_random').task.set_randomization_scale(0.5)
