"""Measures the effect of robel_dm's documented deviations from ROBEL 0.1.2.

docs/fidelity.md quotes these figures. Each one compares what
robel_dm computes with what ROBEL's code computed, on robel_dm's own
episodes:
  * Stand/Orient `center_distance_cost`: ROBEL's norm took the torso height
    (from its frame origin 0.3 m up) into the "horizontal" distance; per-step
    and per-episode cost difference on a crouched Stand episode (holding the
    crouch), a reference-controller Stand episode and a standing Orient
    episode.
  * D'Claw position-safety counter: ROBEL counted a joint only within 5 deg of
    a limit, on either side, so a joint more than 5 deg beyond its range was
    not counted; how often that happens under random actions.
  * D'Kitty Orient: ROBEL's yaw hinge stopped at +-3.14 rad; the share of
    OrientRandom episodes whose shortest turn crosses it.
  * Screw: ROBEL's valve hinge stopped at +-6.28 rad; the share of
    ScrewRandom episodes whose goal passes it.
  * Observation noise: ROBEL computed rewards from the noisy observations;
    the per-step difference that makes to PoseRandomDynamics'
    `pose_error_cost`.

    MUJOCO_GL=egl python benchmarks/deviations.py [--episodes 20]
"""

import argparse

import numpy as np

from robel_dm import geometry, policies, suite
from robel_dm.entities import dkitty

# ROBEL's D'Claw position-safety margin, rad (5 deg).
_CLAW_MARGIN = np.deg2rad(5.0)
# ROBEL's D'Kitty yaw hinge limit, rad.
_YAW_LIMIT = 3.14
# ROBEL's valve hinge limit, rad.
_VALVE_LIMIT = 6.28


def _center_distance_difference(domain_task, policy_name, hold=None):
  """Per-step cost difference ROBEL minus robel_dm over one episode.

  Returns:
    (mean per step, largest per step, episode sum), all >= 0 as costs are
    negative: ROBEL's cost is that much larger in magnitude.
  """
  env = suite.load(*domain_task, seed=0)
  weight = env.task.reward_constants.center_distance_weight
  timestep = env.reset()
  if hold is not None:
    action = env.task.normalize_joint_targets(hold)
    policy = lambda timestep: action  # noqa: E731
  else:
    policy = policies.make_policy(policy_name, env, seed=0)
  differences = []
  while not timestep.last():
    timestep = env.step(policy(timestep))
    root_pos = timestep.observation['root_pos']
    robel = np.linalg.norm(root_pos)  # Height included.
    ours = np.linalg.norm(root_pos[:2])
    differences.append(weight * (robel - ours))
  env.close()
  differences = np.array(differences)
  return differences.mean(), differences.max(), differences.sum()


def _claw_uncounted_share(task, episodes):
  """Share of steps with a joint > 5 deg beyond its action range (ROBEL did
  not count it), and robel_dm's mean position count per step."""
  env = suite.load('dclaw', task, seed=0)
  policy = policies.make_policy('random', env, seed=0)
  joints = env.physics.bind(env.task.robot.joints)
  ranges = env.physics.bind(env.task.robot.actuators).ctrlrange
  low, high = ranges[:, 0], ranges[:, 1]
  steps = beyond_steps = beyond_joints = counted = 0
  for _ in range(episodes):
    timestep = env.reset()
    while not timestep.last():
      timestep = env.step(policy(timestep))
      qpos = joints.qpos
      beyond = (qpos < low - _CLAW_MARGIN) | (qpos > high + _CLAW_MARGIN)
      steps += 1
      beyond_steps += bool(beyond.any())
      beyond_joints += int(beyond.sum())
      counted += int(timestep.observation['safety'][0])
  env.close()
  return beyond_steps / steps, beyond_joints / steps, counted / steps


def _orient_long_way_share(episodes):
  """Share of orient_random resets whose shortest turn crosses +-3.14."""
  env = suite.load('dkitty', 'orient_random', seed=0)
  root = env.physics.bind(env.task.root_joint)
  crossing = 0
  for _ in range(episodes):
    env.reset()
    w, _, _, z = root.qpos[3:7]
    yaw = 2 * np.arctan2(z, w)
    target_x, target_y = env.task.target
    target_yaw = np.arctan2(target_y, target_x) - np.pi / 2
    turn = geometry.wrap_angle(target_yaw - yaw)
    crossing += abs(yaw + turn) > _YAW_LIMIT
  env.close()
  return crossing / episodes


def _screw_past_limit_share(episodes):
  """Share of screw_random episodes whose goal ends beyond +-6.28 rad."""
  env = suite.load('dclaw', 'screw_random', seed=0)
  hold = env.task.normalize_joint_targets(env.physics.bind(
    env.task.robot.joints).qpos)  # fmt: skip
  past = 0
  for _ in range(episodes):
    env.reset()
    start = env.task.goal
    env.step(hold)
    per_step = env.task.goal - start
    past += abs(start + env.task.episode_steps * per_step) > _VALVE_LIMIT
  env.close()
  return past / episodes


def _noisy_pose_cost_difference(episodes):
  """Mean |pose_error_cost from noisy minus from true joint angles| per
  step in pose_random_dynamics, and the mean |cost| for scale."""
  env = suite.load('dclaw', 'pose_random_dynamics', seed=0)
  policy = policies.make_policy('random', env, seed=0)
  differences, costs = [], []
  for _ in range(episodes):
    timestep = env.reset()
    while not timestep.last():
      timestep = env.step(policy(timestep))
      noisy = -np.linalg.norm(timestep.observation['qpos_error'])
      true = env.task.reward_terms['pose_error_cost']
      differences.append(abs(noisy - true))
      costs.append(abs(true))
  env.close()
  return float(np.mean(differences)), float(np.mean(costs))


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--episodes', type=int, default=20)
  parser.add_argument('--orient_resets', type=int, default=10000)
  args = parser.parse_args()

  print('center_distance_cost, ROBEL minus robel_dm (cost magnitude):')
  print(f'  {"episode":38s} {"mean/step":>10s} {"max/step":>10s} '
        f'{"episode":>10s}')  # fmt: skip
  cases = (
    ('Stand, holding the crouch', ('dkitty', 'stand_fixed'), None,
     dkitty.CROUCHED_POSE),
    ('Stand, reference controller', ('dkitty', 'stand_fixed'), 'reference',
     None),
    ('Orient, holding the standing pose', ('dkitty', 'orient_fixed'), None,
     dkitty.STANDING_POSE),
  )  # fmt: skip
  for label, task, policy, hold in cases:
    mean, largest, total = _center_distance_difference(task, policy, hold)
    print(f'  {label:38s} {mean:10.4f} {largest:10.4f} {total:10.2f}')

  print('\nD\'Claw joints > 5 deg beyond their range under random actions '
        f'({args.episodes} episodes):')  # fmt: skip
  print(f'  {"task":14s} {"steps with one":>15s} {"joints/step":>12s} '
        f'{"robel_dm count/step":>20s}')  # fmt: skip
  for task in ('pose_random', 'turn_random', 'screw_random'):
    share, per_step, counted = _claw_uncounted_share(task, args.episodes)
    print(f'  {task:14s} {share:15.4f} {per_step:12.4f} {counted:20.3f}')

  share = _orient_long_way_share(args.orient_resets)
  print(f'\norient_random: shortest turn crosses +-3.14 rad in {share:.1%} '
        f'of {args.orient_resets} resets')  # fmt: skip
  share = _screw_past_limit_share(args.orient_resets)
  print(f'screw_random: goal passes +-6.28 rad in {share:.1%} '
        f'of {args.orient_resets} episodes')  # fmt: skip
  difference, cost = _noisy_pose_cost_difference(args.episodes)
  print(f'pose_random_dynamics: |pose_error_cost(noisy) - (true)| = '
        f'{difference:.4f} per step (mean |cost| {cost:.4f})')  # fmt: skip


if __name__ == '__main__':
  main()
