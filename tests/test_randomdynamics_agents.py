"""The agents for RandomDynamics tasks: `sac_privileged` and
`sac_asymmetric` (the task's privileged observation) and `sac_curriculum`
(a curriculum over the randomization). The task-level parts are tested in
test_privileged.py and test_curriculum.py.
"""

import numpy as np
import pytest

pytest.importorskip('stable_baselines3', reason='needs robel_dm[learn]')
pytest.importorskip('sbx', reason='needs robel_dm[learn]')

from robel_dm import evaluation, policies  # noqa: E402
from robel_dm.learning import agents, run_config, training  # noqa: E402
from robel_dm.learning import gym as robel_gym  # noqa: E402

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning')


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
  # The privileged actor of the dynamics alone reads them in training and
  # in every evaluation of its policy.
  dynamics = _config('sac_privileged_dynamics')
  assert dynamics.training_task_kwargs == {'privileged': 'dynamics'}
  assert dynamics.policy_task_kwargs == {'privileged': 'dynamics'}
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


@pytest.mark.parametrize(
  'algo', ['sac_asymmetric', 'sac_privileged', 'sac_privileged_dynamics']
)
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
  # The episode ran with the observation the policy reads.
  assert results['task_kwargs'].get('privileged', False) == policy.privileged
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


def test_curriculum_rises_over_its_share_of_the_budget():
  scales = [training.curriculum_scale(0.5, done, 60_000) for done in
            (0, 15_000, 30_000, 45_000)]  # fmt: skip
  assert scales == [0.0, 0.5, 1.0, 1.0]


def test_curriculum_agent_needs_a_randomized_task():
  config = run_config.RunConfig(
    domain='dclaw', task='pose_random', algo='sac_curriculum'
  )
  with pytest.raises(ValueError, match='needs a RandomDynamics task, not'):
    config.check()


@pytest.mark.slow
def test_curriculum_run_sets_the_scale_before_each_chunk(tmp_path, monkeypatch):
  seen = []
  original = robel_gym.RobelEnv.set_randomization_scale

  def spy(self, scale):
    seen.append(scale)
    original(self, scale)

  monkeypatch.setattr(robel_gym.RobelEnv, 'set_randomization_scale', spy)
  config = run_config.RunConfig(
    domain='dclaw', task='pose_random_dynamics', algo='sac_curriculum',
    steps=800, eval_every=200, eval_episodes=1,
  )  # fmt: skip
  training.train(config, tmp_path, log=lambda line: None)
  # Half of 800 steps: 0, 0.5, then the task's full ranges.
  assert seen == [0.0, 0.5, 1.0, 1.0]
