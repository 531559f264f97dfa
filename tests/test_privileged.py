"""The privileged observation (`task_kwargs={'privileged': True}`) and the
agents that read it: `sac_privileged` (actor and critics) and
`sac_asymmetric` (critics only).

Expected values come from ROBEL's randomization ranges (`robel_spec`
constants where it has them) and the model, not from the code under test.
"""

import numpy as np
import pytest

from robel_dm import suite
from robel_dm.arenas import floor

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning')


def test_privileged_observation_is_last_and_sized_before_compiling(
  dynamics_task_id,
):
  task_id = dynamics_task_id
  env = suite.load(*task_id, task_kwargs={'privileged': True}, seed=3)
  timestep = env.reset()
  task = env.task
  assert task.agent_observation_keys[-1] == 'privileged'
  privileged = timestep.observation['privileged']
  assert task.flatten_observation(timestep.observation).size == (
    task.agent_observation_size
  )
  plain = suite.load(*task_id, seed=3)
  assert task.agent_observation_size == (
    plain.task.agent_observation_size + privileged.size
  )
  assert np.all(privileged >= -1.0) and np.all(privileged <= 1.0)
  env.close()
  plain.close()


def test_dclaw_draws_are_the_model_values_scaled_over_the_ranges():
  env = suite.load(
    'dclaw', 'pose_random_dynamics', task_kwargs={'privileged': True}, seed=5
  )
  for _ in range(3):  # A new draw every episode.
    privileged = env.reset().observation['privileged']
    joints = env.physics.bind(env.task.robot.joints)
    actuators = env.physics.bind(env.task.robot.actuators)

    def unscaled(scaled, low, high):
      return low + (scaled + 1.0) / 2.0 * (high - low)

    # ROBEL's D'Claw ranges: damping U(0.005, 0.1) and friction loss
    # U(0.001, 0.005) per joint, one servo gain U(1, 3).
    np.testing.assert_allclose(
      unscaled(privileged[:9], 0.005, 0.1), joints.damping
    )
    np.testing.assert_allclose(
      unscaled(privileged[9:18], 0.001, 0.005), joints.frictionloss
    )
    np.testing.assert_allclose(
      unscaled(privileged[18], 1.0, 3.0), actuators.gainprm[:, 0]
    )
    assert privileged.size == 19
  env.close()


def test_dynamics_draws_name_the_privileged_observations_parts():
  env = suite.load(
    'dkitty', 'orient_random_dynamics', task_kwargs={'privileged': True}
  )
  for _ in range(2):  # A new draw every episode.
    privileged = env.reset().observation['privileged']
    draws = env.task.dynamics_draws
    # D'Kitty's locomotion ranges: one damping, one friction loss and one
    # servo gain for all joints, contact friction (3), total mass.
    assert list(draws) == [
      'damping', 'friction_loss', 'actuator_kp', 'geom_friction', 'total_mass'
    ]  # fmt: skip
    assert [d.size for d in draws.values()] == [1, 1, 1, 3, 1]
    np.testing.assert_array_equal(
      np.concatenate(list(draws.values())), privileged[:7]
    )
    # Servo gain U(2.8, 3.2), scaled to [-1, 1].
    gain = env.physics.bind(env.task.robot.actuators).gainprm[0, 0]
    assert draws['actuator_kp'][0] == pytest.approx((gain - 3.0) / 0.2)
  assert suite.load('dclaw', 'pose_random').task.dynamics_draws == {}
  env.close()


def test_dkitty_sees_the_terrain_under_its_torso():
  env = suite.load(
    'dkitty', 'walk_random_dynamics', task_kwargs={'privileged': True}, seed=2
  )
  env.reset()
  arena = env.task.arena
  heights = arena.terrain_heights
  size = int(np.sqrt(heights.size))
  # ROBEL's field: 120 x 120 cells over +-4.5 m; rows along y. A 5 cm bump
  # in the cell of row 70, column 40, the rest flat at 0.
  heights[:] = 0.0
  heights[70 * size + 40] = 0.05
  centre = -4.5 + 9.0 * np.array([40, 70]) / (size - 1)
  expected = -np.ones(floor.TERRAIN_PATCH**2)
  expected[floor.TERRAIN_PATCH**2 // 2] = 1.0
  np.testing.assert_array_equal(arena.terrain_around(centre), expected)
  # One cell further along x: the bump one column to the left.
  shifted = arena.terrain_around(centre + [9.0 / (size - 1), 0.0])
  assert shifted[floor.TERRAIN_PATCH**2 // 2 - 1] == 1.0
  # The observation holds the patch under the torso where it is.
  patch = env.step(np.zeros(12)).observation['privileged'][-49:]
  torso = env.physics.bind(env.task.robot.torso).xpos
  np.testing.assert_array_equal(patch, arena.terrain_around(torso))
  env.close()


def test_dynamics_only_leaves_the_terrain_out():
  env = suite.load(
    'dkitty', 'stand_random_dynamics', task_kwargs={'privileged': 'dynamics'}
  )
  everything = suite.load(
    'dkitty', 'stand_random_dynamics', task_kwargs={'privileged': True}
  )
  # Damping, friction loss, gain, contact friction (3), total mass.
  assert env.reset().observation['privileged'].shape == (7,)
  assert everything.task.agent_observation_size == (
    env.task.agent_observation_size + floor.TERRAIN_PATCH**2
  )
  with pytest.raises(ValueError, match='privileged must be one of'):
    suite.load(
      'dkitty', 'stand_random_dynamics', task_kwargs={'privileged': 'all'}
    )


def test_privileged_observation_needs_randomized_dynamics():
  with pytest.raises(ValueError, match='need randomized dynamics'):
    suite.load('dclaw', 'pose_random', task_kwargs={'privileged': True})


def test_default_observation_unchanged():
  keys = suite.load('dclaw', 'pose_random_dynamics').task
  assert 'privileged' not in keys.agent_observation_keys


def test_no_robot_gives_privileged_observations(tmp_path):
  # Refused before any bus is opened: the device path does not exist.
  with pytest.raises(ValueError, match='a robot gives none'):
    suite.load(
      'dclaw', 'pose_random_dynamics', task_kwargs={'privileged': True},
      robot=suite.RobotOptions(str(tmp_path / 'no_such_device')),
    )  # fmt: skip
