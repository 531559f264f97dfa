"""Learning under a safety budget: SAC with a Lagrange multiplier on
ROBEL's violations (robel_dm.learning.sac.SafetyConstraint)."""

import numpy as np
import pytest

gymnasium = pytest.importorskip('gymnasium', reason='needs robel_dm[learn]')
pytest.importorskip('sbx', reason='needs robel_dm[learn]')

from robel_dm.learning import agents, safety  # noqa: E402
from robel_dm.learning import sac as sac_lib  # noqa: E402


class _Violating(gymnasium.Env):
  """A stand-in task whose every step counts 3 velocity violations while
  its action's first component is positive, none otherwise."""

  def __init__(self):
    self.observation_space = gymnasium.spaces.Box(-1, 1, (4,), np.float32)
    self.action_space = gymnasium.spaces.Box(-1, 1, (2,), np.float32)
    self._t = 0

  def reset(self, *, seed=None, options=None):
    self._t = 0
    return self.observation_space.sample(), {}

  def step(self, action):
    self._t += 1
    fast = 3.0 if action[0] > 0 else 0.0
    info = {'safety': {'position': 0.0, 'velocity': fast, 'current': 0.0}}
    return self.observation_space.sample(), 1.0, False, self._t == 10, info


def _model():
  from stable_baselines3.common.logger import Logger  # noqa: PLC0415
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  agents.single_thread()
  model = sac_lib.SAC(
    'MlpPolicy',
    DummyVecEnv([_Violating]),
    seed=0,
    verbose=0,
    train_freq=8,
    gradient_steps=8,
    learning_starts=16,
    batch_size=4,
    buffer_size=1000,
    policy_kwargs={'net_arch': [8, 8]},
  )
  # SB3's default logger makes a folder in /tmp per learn() call.
  model.set_logger(Logger(folder=None, output_formats=[]))
  return model


def test_the_multiplier_rises_over_budget_and_falls_under_it():
  constraint = safety.SafetyConstraint(budget=10, learning_rate=0.5)
  ended, running = np.array([True]), np.array([False])
  constraint.observe(np.array([15.0]), running)
  assert constraint.multiplier == 0.0  # Only at an episode's end.
  constraint.observe(np.array([15.0]), ended)  # 30 in the episode: 2x over.
  assert constraint.multiplier == pytest.approx(0.5 * 2.0)
  constraint.observe(np.array([5.0]), ended)  # Half the budget.
  assert constraint.multiplier == pytest.approx(1.0 - 0.5 * 0.5)
  for _ in range(10):
    constraint.observe(np.array([0.0]), ended)
  assert constraint.multiplier == 0.0  # Never negative.
  constraint.observe(np.array([1e6]), ended)  # A wild episode, bounded.
  assert constraint.multiplier == pytest.approx(0.5 * 10)
  with pytest.raises(ValueError, match='budget must be >= 0'):
    safety.SafetyConstraint(budget=-1)


@pytest.mark.slow
def test_replayed_rewards_pay_the_current_multiplier_per_violation():
  model = _model()
  model.safety = safety.SafetyConstraint(budget=0, learning_rate=0.0)
  model.learn(40)
  buffer = model.replay_buffer
  held = buffer.pos
  violations = buffer.violations[:held, 0]
  # Every stored step has the violations its step reported.
  positive = buffer.actions[:held, 0, 0] > 0
  np.testing.assert_array_equal(violations, np.where(positive, 3.0, 0.0))
  model.safety.multiplier = 0.25
  sample = model.sample_replay(200)
  expected = {1.0, 1.0 - 0.25 * 3.0}
  assert set(np.round(sample.rewards, 6).tolist()) == expected


@pytest.mark.slow
def test_without_a_budget_rewards_are_the_tasks():
  model = _model()
  model.learn(40)
  assert getattr(model.replay_buffer, 'violations', None) is None
  assert set(model.sample_replay(50).rewards.tolist()) == {1.0}
