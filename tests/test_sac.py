"""The default agent's SAC: sbx's updates, acting and replay in numpy."""

import os

import numpy as np
import pytest

gymnasium = pytest.importorskip('gymnasium', reason='needs robel_dm[learn]')
pytest.importorskip('sbx', reason='needs robel_dm[learn]')

from robel_dm.learning import actor, agents  # noqa: E402
from robel_dm.learning import sac as sac_lib  # noqa: E402

# Every test builds sbx models (the quick tier, -m 'not slow', leaves them
# out).
pytestmark = pytest.mark.slow


class _Random(gymnasium.Env):
  """A stand-in task: random observations, reward and episode ends."""

  def __init__(self):
    self.observation_space = gymnasium.spaces.Box(-1, 1, (7,), np.float32)
    self.action_space = gymnasium.spaces.Box(-1, 1, (3,), np.float32)
    self._rng = np.random.default_rng(0)
    self._t = 0

  def reset(self, *, seed=None, options=None):
    self._t = 0
    return self.observation_space.sample(), {}

  def step(self, action):
    self._t += 1
    reward = float(self._rng.normal())
    end = self._t == 10
    return self.observation_space.sample(), reward, False, end, {}


def _model(seed=0, **kwargs):
  from stable_baselines3.common.logger import Logger  # noqa: PLC0415
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  agents.single_thread()
  settings = {
    'train_freq': 8,
    'gradient_steps': 8,
    'learning_starts': 16,
    'batch_size': 4,
    'buffer_size': 1000,
    'policy_kwargs': {'net_arch': [8, 8]},
    **kwargs,
  }
  model = sac_lib.SAC(
    'MlpPolicy', DummyVecEnv([_Random]), seed=seed, verbose=0, **settings
  )
  # SB3's default logger makes a folder in /tmp per learn() call.
  model.set_logger(Logger(folder=None, output_formats=[]))
  return model


def test_numpy_acting_samples_sbx_actors_distribution():
  model = _model()
  model.learn(64)
  policy = model.policy
  observations = np.random.default_rng(1).uniform(-1, 1, (5, 7))
  observations = observations.astype(np.float32)
  distribution = policy.actor_state.apply_fn(
    policy.actor_state.params, observations
  ).distribution
  mean = np.asarray(distribution.mean())
  std = np.asarray(distribution.stddev())
  np.testing.assert_allclose(
    policy._predict(observations, deterministic=True),
    np.tanh(mean),
    rtol=1e-5,
    atol=1e-6,
  )
  # A sample is tanh(mean + std * noise) with the policy's own noise.
  policy.rng = np.random.default_rng(7)
  sample = policy._predict(observations)
  noise = np.random.default_rng(7).standard_normal(mean.shape)
  np.testing.assert_allclose(
    sample, np.tanh(mean + std * noise), rtol=1e-4, atol=1e-5
  )


def test_the_numpy_actor_follows_each_update():
  model = _model()
  model.learn(32)
  before = model.policy.numpy_actor().mean(np.zeros(7, np.float32))
  model.train(gradient_steps=8, batch_size=4)
  after = model.policy.numpy_actor().mean(np.zeros(7, np.float32))
  expected = actor.StochasticActor(agents.sac_actor_layers(model))
  np.testing.assert_array_equal(after, expected.mean(np.zeros(7, np.float32)))
  assert not np.array_equal(before, after)


def test_replay_samples_are_stored_transitions_with_timeouts_not_terminal():
  model = _model()
  model.learn(40)
  buffer = model.replay_buffer
  stored = {buffer.observations[i, 0].tobytes(): i for i in range(buffer.pos)}
  sample = model.sample_replay(200)
  for k in range(200):
    i = stored[sample.observations[k].tobytes()]
    np.testing.assert_array_equal(sample.actions[k], buffer.actions[i, 0])
    np.testing.assert_array_equal(
      sample.next_observations[k], buffer.next_observations[i, 0]
    )
    assert sample.rewards[k] == np.float32(buffer.rewards[i, 0])
    # Every episode of the stand-in ends by its time limit: never terminal.
    assert sample.dones[k] == 0.0
  assert buffer.dones[: buffer.pos, 0].sum() == 4  # 4 episodes ended.
  assert len({row.tobytes() for row in sample.observations}) > 30
  assert np.all(sample.discounts == np.float32(model.gamma))


def test_a_saved_model_continues_its_random_streams(tmp_path):
  model = _model()
  model.learn(48)
  model.save(tmp_path / 'model.zip')
  loaded = sac_lib.SAC.load(tmp_path / 'model.zip', env=model.get_env())
  assert isinstance(loaded.policy, sac_lib.NumpyActingPolicy)
  for one in (model, loaded):
    one.replay_buffer = model.replay_buffer
  np.testing.assert_array_equal(
    model.sample_replay(16).observations, loaded.sample_replay(16).observations
  )
  observation = np.zeros((1, 7), np.float32)
  np.testing.assert_array_equal(
    model.policy._predict(observation), loaded.policy._predict(observation)
  )
  np.testing.assert_array_equal(np.asarray(model.key), np.asarray(loaded.key))


def test_seeds_give_their_own_streams():
  one, same, other = _model(seed=1), _model(seed=1), _model(seed=2)
  draws = [m.policy.rng.standard_normal(4) for m in (one, same, other)]
  np.testing.assert_array_equal(draws[0], draws[1])
  assert not np.array_equal(draws[0], draws[2])
  replay = [m.replay_rng.integers(0, 1000, 8) for m in (one, same, other)]
  np.testing.assert_array_equal(replay[0], replay[1])
  assert not np.array_equal(replay[0], replay[2])


def test_compiled_updates_are_cached_for_later_runs(tmp_path):
  import os  # noqa: PLC0415
  import subprocess  # noqa: PLC0415
  import sys  # noqa: PLC0415

  env = {
    key: value
    for key, value in os.environ.items()
    if not key.startswith(('JAX_', 'XLA_'))
  }
  env['XDG_CACHE_HOME'] = str(tmp_path)
  program = (
    'from robel_dm.learning import agents; agents.single_thread(); '
    'import jax; jax.jit(lambda x: x * 2 + 1)(1.0).block_until_ready()'
  )
  subprocess.run([sys.executable, '-c', program], env=env, check=True)
  cache = tmp_path / 'robel_dm' / 'jax'
  assert any(cache.iterdir()), 'no compilation was cached'


@pytest.mark.skipif(
  not hasattr(os, 'sched_setaffinity') or len(os.sched_getaffinity(0)) < 2,
  reason='needs Linux and two cores',
)
def test_jax_starts_with_one_worker_and_every_thread_keeps_its_cores():
  import subprocess  # noqa: PLC0415
  import sys  # noqa: PLC0415

  env = {
    key: value
    for key, value in os.environ.items()
    if not key.startswith(('JAX_', 'XLA_'))
  }
  program = (
    'import os, pathlib\n'
    'from robel_dm.learning import agents\n'
    'cores = os.sched_getaffinity(0)\n'
    'agents.single_thread()\n'
    'import jax\n'
    'jax.jit(lambda x: x @ x)(jax.numpy.ones((64, 64))).block_until_ready()\n'
    "threads = list(pathlib.Path('/proc/self/task').iterdir())\n"
    "names = [(t / 'comm').read_text().strip() for t in threads]\n"
    "print(names.count('tf_XLAEigen'))\n"
    'print(all(os.sched_getaffinity(int(t.name)) == cores for t in threads))\n'
  )
  out = subprocess.run(
    [sys.executable, '-c', program],
    env=env,
    check=True,
    capture_output=True,
    text=True,
  ).stdout.split()
  # XLA's pool has a worker per core the process could use when JAX
  # started: one, so that an update runs on one core.
  assert out == ['1', 'True']


class _Other(_Random):
  """Another stand-in task with more observations."""

  def __init__(self):
    super().__init__()
    self.observation_space = gymnasium.spaces.Box(-1, 1, (9,), np.float32)


def test_a_warm_start_takes_the_networks_and_nothing_else(tmp_path):
  import jax  # noqa: PLC0415
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  source = _model()
  source.learn(40)
  source.save(str(tmp_path / 'checkpoint.zip'))
  agent = agents.get('sac')
  env = DummyVecEnv([_Random])
  model = agents.warm_start(agent, tmp_path / 'checkpoint.zip', env, 7, 500)
  same = jax.tree_util.tree_map(
    lambda a, b: bool(np.array_equal(a, b)),
    model.policy.actor_state.params,
    source.policy.actor_state.params,
  )
  assert all(jax.tree_util.tree_leaves(same))
  assert model.num_timesteps == 0
  assert model.replay_buffer.pos == 0 and model.replay_buffer.buffer_size == 500
  fresh = agents.warm_start(agent, tmp_path / 'checkpoint.zip', env, 7, 500)
  assert model.replay_rng.integers(1 << 30) == fresh.replay_rng.integers(
    1 << 30
  )
  with pytest.raises(ValueError, match='[Oo]bservation spaces do not match'):
    agents.warm_start(
      agent, tmp_path / 'checkpoint.zip', DummyVecEnv([_Other]), 7, 500
    )
