"""Reward constants are passed in (`task_kwargs={'reward': ...}`), ROBEL's
by default: a sweep or a curriculum over a weight needs no monkeypatching."""

import dataclasses

import numpy as np
import pytest

from robel_dm import suite
from robel_dm.tasks import dclaw_pose, dkitty_walk


def _summed_terms(domain, task, **task_kwargs):
  """Each reward term summed over 6 steps of fast, alternating actions."""
  env = suite.load(domain, task, seed=3, task_kwargs=task_kwargs)
  env.reset()
  spec = env.action_spec()
  totals = {}
  for step in range(6):
    env.step(np.full(spec.shape, 1.0 if step % 2 else -1.0))
    for name, value in env.task.reward_terms.items():
      totals[name] = totals.get(name, 0.0) + value
  env.close()
  return totals


@pytest.mark.slow
@pytest.mark.parametrize('domain, task', suite.ALL_TASKS)
def test_every_task_runs_with_robels_constants_by_default(domain, task):
  env = suite.load(domain, task, seed=0)
  assert env.task.reward_constants is type(env.task).DEFAULT_REWARD
  env.close()


@pytest.mark.slow
def test_a_weight_given_as_a_mapping_changes_its_term_only():
  # Pose's rate limit keeps joints under ROBEL's pi rad/s: count slower ones.
  slow = {'fast_joint_speed': 0.5}
  robel = _summed_terms('dclaw', 'pose_fixed', reward=slow)
  heavier = _summed_terms(
    'dclaw', 'pose_fixed', reward={**slow, 'joint_vel_weight': 0.2}
  )
  assert heavier['joint_vel_cost'] == pytest.approx(2 * robel['joint_vel_cost'])
  assert robel['joint_vel_cost'] != 0.0
  assert heavier['pose_error_cost'] == robel['pose_error_cost']


def test_a_whole_dataclass_replaces_the_constants():
  constants = dataclasses.replace(dkitty_walk.REWARD, bonus_small=0.0)
  env = suite.load('dkitty', 'walk_fixed', task_kwargs={'reward': constants})
  assert env.task.reward_constants.bonus_small == 0.0
  assert dkitty_walk.REWARD.bonus_small == 5.0  # The default is untouched.
  env.close()


@pytest.mark.parametrize(
  'reward, message',
  [
    ({'joint_vel_wieght': 0.2}, r"unknown constants \['joint_vel_wieght'\]"),
    ({'joint_vel_weight': 'heavy'}, 'must be a number'),
    ({'joint_vel_weight': float('nan')}, 'must be finite'),
    (dkitty_walk.REWARD, 'must be a PoseReward or a mapping'),
  ],
)
def test_bad_constants_are_named(reward, message):
  with pytest.raises(ValueError, match=message):
    suite.load('dclaw', 'pose_fixed', task_kwargs={'reward': reward})


def test_the_default_is_robels():
  assert dclaw_pose.REWARD.joint_vel_weight == 0.1
