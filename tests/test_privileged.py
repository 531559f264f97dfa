"""The privileged observation (`task_kwargs={'privileged': True}`) and the
agents that read it: `sac_privileged` (actor and critics) and
`sac_asymmetric` (critics only).

Expected values come from ROBEL's randomization ranges (`robel_spec`
constants where it has them) and the model, not from the code under test.
"""

import numpy as np
import pytest

from robel_dm import evaluation, policies, suite
from robel_dm.arenas import floor
from robel_dm.learning import agents, run_config, training

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


def _config(algo, **kwargs):
  return run_config.RunConfig(
    domain='dclaw', task='pose_random_dynamics', algo=algo, **kwargs
  )


def test_which_env_reads_the_privileged_observation():
  asymmetric, privileged, plain = (
    _config('sac_asymmetric'),
    _config('sac_privileged'),
    _config('sac'),
  )
  # The asymmetric critics see the dynamics, not the terrain.
  assert asymmetric.training_task_kwargs == {'privileged': 'dynamics'}
  assert asymmetric.policy_task_kwargs == {}
  assert privileged.training_task_kwargs == {'privileged': True}
  assert privileged.policy_task_kwargs == {'privileged': True}
  assert plain.training_task_kwargs == plain.policy_task_kwargs == {}


def _model(algo):
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  config = _config(algo)
  env = DummyVecEnv([lambda: training.make_env(config, 0)])
  return agents.build(config.agent, env, 0, (32, 32), 1000), env


def test_asymmetric_actor_ignores_what_only_the_critics_see():
  model, env = _model('sac_asymmetric')
  privileged = env.get_attr('privileged_size')[0]
  observed = env.observation_space.shape[0] - privileged
  assert privileged == 19
  # The actor's first layer takes the robot's share, the critics' all.
  actor_kernel = model.policy.actor_state.params['params']['Dense_0']
  assert actor_kernel['kernel'].shape[0] == observed
  critic_inputs = {
    leaf.shape[1]
    for leaf in _leaves(model.policy.qf_state.params)
    if leaf.ndim == 3  # (critics, inputs, units) of the vectorized critic.
  }
  assert env.observation_space.shape[0] + 9 in critic_inputs
  observation = env.reset()
  changed = observation.copy()
  changed[:, observed:] = -changed[:, observed:] + 0.5
  np.testing.assert_array_equal(
    model.predict(observation, deterministic=True)[0],
    model.predict(changed, deterministic=True)[0],
  )
  env.close()


def _leaves(tree):
  if isinstance(tree, dict):
    for value in tree.values():
      yield from _leaves(value)
  else:
    yield np.asarray(tree)


@pytest.mark.parametrize('algo', ['sac_asymmetric', 'sac_privileged'])
def test_privileged_agents_need_a_randomized_task(algo):
  config = run_config.RunConfig(domain='dclaw', task='pose_random', algo=algo)
  with pytest.raises(ValueError, match='needs a RandomDynamics task, not'):
    config.check()
  _config(algo).check()


@pytest.mark.slow
@pytest.mark.parametrize('algo', ['sac_asymmetric', 'sac_privileged'])
def test_trained_policy_reads_what_its_actor_saw(tmp_path, algo):
  config = _config(algo, steps=600, eval_every=600, eval_episodes=1)
  training.train(config, tmp_path, log=lambda line: None)
  policy = policies.load(tmp_path / 'policy_best.npz')
  assert policy.privileged == (algo == 'sac_privileged')
  lines = []
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_random_dynamics', 1, policy=str(tmp_path / 'policy.npz'),
      log=lines.append,
    )
  )  # fmt: skip
  adopted = 'the policy learned with task option privileged=True: ' + (
    'evaluating with it'
  )
  assert (adopted in lines) == policy.privileged
  assert results['episodes'] == 1 or results['success_rate'] >= 0
  if policy.privileged:
    with pytest.raises(
      policies.PolicyError, match='trained with privileged True, not False'
    ):
      evaluation.evaluate(
        evaluation.EvalConfig(
          'dclaw', 'pose_random_dynamics', 1,
          policy=str(tmp_path / 'policy.npz'),
          task_kwargs={'privileged': False},
        )
      )  # fmt: skip


def test_a_policy_saved_before_the_prefix_actor_existed_still_acts():
  # Pickled SAC policies of older runs have no `observed`; a resumed run
  # must act with them as before.
  model, env = _model('sac')
  del model.policy.__dict__['observed']
  observation = env.reset()
  assert model.predict(observation, deterministic=True)[0].shape == (1, 9)
  env.close()


def test_no_robot_gives_privileged_observations(tmp_path):
  # Refused before any bus is opened: the device path does not exist.
  with pytest.raises(ValueError, match='a robot gives none'):
    suite.load(
      'dclaw', 'pose_random_dynamics', task_kwargs={'privileged': True},
      robot=suite.RobotOptions(str(tmp_path / 'no_such_device')),
    )  # fmt: skip
