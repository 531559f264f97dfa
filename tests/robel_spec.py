"""ROBEL's numbers, and helpers shared by the test modules.

The numbers are written out from docs/robel_reference.md (sections 1, 2.0, 2.3,
2.4, 3.4 and 6), independently of robel_dm, so that the tests compare
robel_dm with ROBEL rather than with itself.
"""

import math

import numpy as np

PHYSICS_TIMESTEP = 0.0025

# Task families (the first word of a task's name) per domain.
FAMILIES = {
  'dclaw': ('pose', 'turn', 'screw'),
  'dkitty': ('stand', 'orient', 'walk'),
}

# Episode length (control steps) and control timestep (s) per family.
TIMING = {
  'pose': (80, 0.05),
  'turn': (40, 0.1),
  'screw': (80, 0.1),
  'stand': (80, 0.1),
  'orient': (80, 0.1),
  'walk': (160, 0.1),
}

# --- Action map (docs/robel_reference.md section 2.0) -------------------------

DCLAW_ACTION_HIGH = np.tile([0.48, np.pi / 3, np.pi / 2], 3)
DCLAW_ACTION_LOW = -DCLAW_ACTION_HIGH


def _kitty_ranges(right_hip, left_hip, upper, knee):
  """(low, high) arrays over the legs FR, FL, BL, BR (hip, upper, knee)."""
  right, left = [right_hip, upper, knee], [left_hip, upper, knee]
  return tuple(np.array(right + left + left + right).T)


DKITTY_ACTION_LOW, DKITTY_ACTION_HIGH = _kitty_ranges(
  (-0.5, 0.279), (-0.279, 0.5), (0.0, np.pi / 2), (-2.0, 0.0)
)
ACTION_RANGE = {
  'dclaw': (DCLAW_ACTION_LOW, DCLAW_ACTION_HIGH),
  'dkitty': (DKITTY_ACTION_LOW, DKITTY_ACTION_HIGH),
}
# The per-step clamp: a target moves at most this speed x control timestep
# from the current position, rad/s.
MAX_JOINT_SPEED = {'dclaw': 2 * np.pi / 3, 'dkitty': np.pi}

# The D'Kitty's mechanical joint ranges (docs/robel_reference.md section 3.4:
# hips -3.419..0.279 and -0.279..3.419, upper legs +-2.14, knees +-1.57;
# ROBEL's 3.419 and 1.57 are pi + 0.279 and pi / 2 written with 3.14, which
# robel_dm writes exactly).
_HIP = math.pi + 0.279
DKITTY_JOINT_LOW, DKITTY_JOINT_HIGH = _kitty_ranges(
  (-_HIP, 0.279), (-0.279, _HIP), (-2.14, 2.14), (-np.pi / 2, np.pi / 2)
)

# Safety counters (docs/robel_reference.md section 2.3): position margin (rad)
# to the range the counter watches, speed limit (rad/s). ROBEL's D'Claw
# counts near the action range; robel_dm's D'Kitty (ROBEL had no D'Kitty
# counters) near the mechanical joint range, at ROBEL's D'Kitty joint speed
# limit.
SAFETY_MARGIN = np.deg2rad(5.0)
SAFETY_SPEED = {'dclaw': 1.0, 'dkitty': np.pi}
SAFETY_RANGE = {
  'dclaw': (DCLAW_ACTION_LOW, DCLAW_ACTION_HIGH),
  'dkitty': (DKITTY_JOINT_LOW, DKITTY_JOINT_HIGH),
}

# --- ROBEL's default flattened observations -----------------------------------

_VALVE_LAYOUT = (
  ('claw_qpos', 9),
  ('object_x', 1),
  ('object_y', 1),
  ('last_action', 9),
  ('target_error', 1),
)
_KITTY_LAYOUT = (
  ('root_pos', 3),
  ('root_euler', 3),
  ('kitty_qpos', 12),
  ('root_vel', 3),
  ('root_angular_vel', 3),
  ('kitty_qvel', 12),
  ('last_action', 12),
  ('upright', 1),
)
# Key and size of each entry, in order (docs/robel_reference.md sections 2.1,
# 2.2, 2.5-2.7).
LAYOUTS = {
  'pose': (('qpos', 9), ('last_action', 9), ('qpos_error', 9)),
  'turn': _VALVE_LAYOUT,
  'screw': _VALVE_LAYOUT,
  'stand': _KITTY_LAYOUT + (('pose_error', 12),),
  'orient': _KITTY_LAYOUT + (('current_facing', 2), ('desired_facing', 2)),
  'walk': _KITTY_LAYOUT + (('heading', 1), ('target_error', 2)),
}
FLAT_SIZES = {
  'pose': 27,
  'turn': 21,
  'screw': 21,
  'stand': 61,
  'orient': 53,
  'walk': 52,
}

# --- Task ids -----------------------------------------------------------------


def domain(task_id) -> str:
  return task_id[0]


def family(task_id) -> str:
  family = task_id[1].split('_')[0]
  assert family in FAMILIES[task_id[0]], f'unknown family of {task_id}'
  return family


def ids(tasks):
  return [f'{domain}-{task}' for domain, task in tasks]


# --- Policies -----------------------------------------------------------------


def steady_policy(env, seed=0, noise=0.05):
  """A policy under which episodes normally run to their time limit.

  The D'Claw cannot fail: the policy draws uniform random actions. Random
  actions make the D'Kitty fall, so for it the policy holds the leg pose of
  the episode's first timestep (the standing pose, or the pose a Stand reset
  settled in; the current pose until a first timestep comes) with uniform
  noise of +-`noise` on each normalized action. A Stand episode from a
  random pose can still fall.

  Args:
    env: an environment of `suite.load`.
    seed: seed of the noise.
    noise: half-width of the D'Kitty's action noise.

  Returns:
    A function from the current timestep to the next action.
  """
  rng = np.random.default_rng(seed)
  shape = env.action_spec().shape
  if shape == (9,):
    return lambda timestep: rng.uniform(-1.0, 1.0, shape)
  hold = np.zeros(shape)

  def hold_current_pose():
    qpos = env.physics.bind(env.task.robot.joints).qpos
    hold[:] = env.task.normalize_joint_targets(qpos)

  hold_current_pose()

  def policy(timestep):
    if timestep.first():
      hold_current_pose()
    return np.clip(hold + rng.uniform(-noise, noise, shape), -1.0, 1.0)

  return policy
