"""Tests of `robel_dm.environment`: determinism, observation memory, fast path.

The fast path steps all physics substeps of a control step in one MuJoCo call
when nothing observes the intermediate substeps. Adding any substep hook sends
`Environment.step` back to composer's own loop, which is the reference here.
"""

import logging

from dm_control.rl import control
import mujoco
import numpy as np
import pytest
import robel_spec

from robel_dm import suite

# One task of each domain, for tests of the environment machinery.
_ONE_TASK_PER_DOMAIN = (('dclaw', 'turn_fixed'), ('dkitty', 'walk_fixed'))


def _noop_hook(physics, random_state):
  del physics, random_state


def _rollout(env, steps, seed=0):
  """Resets `env` and takes `steps` steps (crossing resets) of the steady
  policy (see `robel_spec.steady_policy`); returns the timesteps."""
  policy = robel_spec.steady_policy(env, seed)
  timesteps = [env.reset()]
  for _ in range(steps):
    timesteps.append(env.step(policy(timesteps[-1])))
  return timesteps


def _crosses_a_reset(timesteps, episode_steps):
  """Whether `timesteps` (from a reset) cross into a second episode, after a
  full episode or after a fall (LAST with discount 0)."""
  ends = [i for i, t in enumerate(timesteps) if t.last()]
  if not ends or ends[0] + 1 >= len(timesteps):
    return False
  end = ends[0]
  full_length = end == episode_steps and timesteps[end].discount == 1.0
  fell = end < episode_steps and timesteps[end].discount == 0.0
  return (full_length or fell) and timesteps[end + 1].first()


def _assert_identical(timesteps_a, timesteps_b):
  assert len(timesteps_a) == len(timesteps_b)
  for a, b in zip(timesteps_a, timesteps_b, strict=True):
    assert a.step_type == b.step_type
    assert a.reward == b.reward  # Bit-identical (None == None at FIRST).
    assert a.discount == b.discount
    assert list(a.observation) == list(b.observation)
    for key in a.observation:
      assert a.observation[key].dtype == b.observation[key].dtype, key
      np.testing.assert_array_equal(a.observation[key], b.observation[key])


# --- Seeded determinism ------------------------------------------------------


@pytest.mark.quick_on_first_task
def test_same_seed_gives_identical_episodes(task_id):
  episode_steps = suite.load(*task_id).task.episode_steps
  steps = episode_steps + 2  # Cross one reset.
  runs = [_rollout(suite.load(*task_id, seed=7), steps) for _ in range(2)]
  assert _crosses_a_reset(runs[0], episode_steps)
  if robel_spec.domain(task_id) == 'dclaw':  # The claw cannot fall.
    assert runs[0][-3].last() and runs[0][-2].first()
  _assert_identical(*runs)


@pytest.mark.slow
def test_different_seeds_give_different_initial_states(random_task_id):
  observations = [
    suite.load(*random_task_id, seed=seed).reset().observation
    for seed in (1, 2)
  ]
  flat = [np.concatenate([np.ravel(v) for v in o.values()]) for o in
          observations]  # fmt: skip
  assert not np.array_equal(*flat)


# Torso features that are the same at every reset: Orient and Walk place the
# D'Kitty level and still at ROBEL's frame origin (Walk also facing +y).
_DETERMINISTIC_AT_RESET = {
  'orient': ('root_pos', 'root_vel', 'root_angular_vel', 'upright'),
  'walk': ('root_pos', 'root_euler', 'root_vel', 'root_angular_vel',
           'upright'),
}  # fmt: skip


@pytest.mark.slow
def test_different_seeds_give_different_dynamics_and_states(dynamics_task_id):
  envs = [suite.load(*dynamics_task_id, seed=seed) for seed in (1, 2)]
  observations = [env.reset().observation for env in envs]
  same = _DETERMINISTIC_AT_RESET.get(robel_spec.family(dynamics_task_id), ())
  for key in envs[0].task.agent_observation_keys:
    if key == 'last_action':
      continue
    differ = not np.array_equal(observations[0][key], observations[1][key])
    assert differ != (key in same), key
  models = [env.physics.model for env in envs]
  assert not np.array_equal(models[0].dof_damping, models[1].dof_damping)
  assert not np.array_equal(
    models[0].actuator_gainprm, models[1].actuator_gainprm
  )
  if robel_spec.domain(dynamics_task_id) == 'dkitty':
    # Also the masses and the terrain.
    assert not np.array_equal(models[0].body_mass, models[1].body_mass)
    assert not np.array_equal(models[0].hfield_data, models[1].hfield_data)


@pytest.mark.slow
def test_fixed_variants_ignore_the_seed(fixed_task_id):
  envs = [suite.load(*fixed_task_id, seed=seed) for seed in (1, 2)]
  _assert_identical(*[[env.reset()] for env in envs])


# --- Observation memory ------------------------------------------------------


def _internal_arrays(env):
  """Arrays held by the task and its physics data."""
  arrays = [v for v in vars(env.task).values() if isinstance(v, np.ndarray)]
  data = env.physics.data
  arrays += [data.qpos, data.qvel, data.ctrl, data.mocap_quat]
  return arrays


def _overlapping_pairs(arrays):
  """Index pairs of arrays whose address ranges overlap (a superset of the
  pairs that share memory), by a sweep over the sorted start addresses."""
  spans = sorted(
    (array.__array_interface__['data'][0], array.nbytes, k)
    for k, array in enumerate(arrays)
  )
  active, pairs = [], []
  for start, size, k in spans:
    active = [(end, j) for end, j in active if end > start]
    pairs += [(j, k) for _, j in active]
    active.append((start + max(size, 1), k))
  return pairs


@pytest.mark.slow
@pytest.mark.parametrize('substep_hook', [False, True], ids=['fast', 'hooked'])
def test_observations_never_share_memory(task_id, substep_hook):
  env = suite.load(*task_id, seed=0)
  if substep_hook:
    env.add_extra_hook('after_substep', _noop_hook)
  env.reset()  # composer compiles the physics at the first reset.
  internal = _internal_arrays(env)
  assert len(internal) > 10
  steps = env.task.episode_steps + 3  # Cross one reset.
  timesteps = _rollout(env, steps)
  assert _crosses_a_reset(timesteps, env.task.episode_steps)
  arrays, owners = [], []
  for i, timestep in enumerate(timesteps):
    for value in timestep.observation.values():
      assert isinstance(value, np.ndarray)
      for array in internal:
        assert not np.shares_memory(value, array)
      arrays.append(value)
      owners.append(i)
  # Every pair of arrays from different timesteps: only overlapping address
  # ranges can share memory, and those must not.
  for j, k in _overlapping_pairs(arrays):
    if owners[j] != owners[k]:
      assert not np.shares_memory(arrays[j], arrays[k]), (owners[j], owners[k])


@pytest.mark.quick_on_first_task
def test_held_observations_do_not_change_later(task_id):
  env = suite.load(*task_id, seed=0)
  steps = env.task.episode_steps + 3
  timesteps = _rollout(env, steps)
  assert _crosses_a_reset(timesteps, env.task.episode_steps)
  copies = [{k: v.copy() for k, v in t.observation.items()} for t in timesteps]
  # More steps and resets must not write into anything handed out.
  policy = robel_spec.steady_policy(env, seed=1)
  timestep, resets = timesteps[-1], 0
  for _ in range(steps):
    timestep = env.step(policy(timestep))
    resets += timestep.first()
  assert resets
  env.reset()
  for timestep, copy in zip(timesteps, copies, strict=True):
    for key, value in timestep.observation.items():
      np.testing.assert_array_equal(value, copy[key])


@pytest.mark.slow
@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_writing_into_an_observation_changes_nothing_else(task):
  env = suite.load(*task, seed=0)
  env.reset()
  timestep = env.step(np.full(env.action_spec().shape, 0.5))
  expected = env.task.flatten_observation(timestep.observation).copy()
  score = float(timestep.observation['score'])
  for value in timestep.observation.values():
    value[...] = 0
  task = env.task
  again = {k: np.array(task.task_observables[k](env.physics)) for k in
           task.agent_observation_keys}  # fmt: skip
  np.testing.assert_array_equal(task.flatten_observation(again), expected)
  assert float(task.task_observables['score'](env.physics)) == score


# --- Fast path ---------------------------------------------------------------


@pytest.mark.quick_on_first_task
def test_fast_path_is_bit_identical_to_composers_loop(task_id):
  fast = suite.load(*task_id, seed=3)
  reference = suite.load(*task_id, seed=3)
  reference.add_extra_hook('after_substep', _noop_hook)
  steps = fast.task.episode_steps + 5  # Cross one reset.
  runs = [_rollout(fast, steps, seed=4), _rollout(reference, steps, seed=4)]
  assert _crosses_a_reset(runs[0], fast.task.episode_steps)
  # The comparison is only meaningful if the two took different paths.
  assert fast._batch_substeps
  assert not reference._batch_substeps
  _assert_identical(*runs)
  np.testing.assert_array_equal(fast.physics.data.qpos,
                                reference.physics.data.qpos)  # fmt: skip
  np.testing.assert_array_equal(fast.physics.data.qacc,
                                reference.physics.data.qacc)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize(
  'integrator',
  [mujoco.mjtIntegrator.mjINT_RK4, mujoco.mjtIntegrator.mjINT_IMPLICITFAST],
  ids=['rk4', 'implicitfast'],
)
@pytest.mark.parametrize(
  'task',
  [('dclaw', 'turn_random'), ('dkitty', 'walk_random_dynamics')],
  ids=['dclaw-turn_random', 'dkitty-walk_random_dynamics'],
)
def test_fast_path_matches_for_other_integrators(task, integrator):
  envs = [suite.load(*task, seed=5) for _ in range(2)]
  envs[1].add_extra_hook('after_substep', _noop_hook)
  for env in envs:
    env.reset()  # The first reset compiles the model: change it afterwards.
    env.physics.model.opt.integrator = integrator
  _assert_identical(*[_rollout(env, 12, seed=6) for env in envs])
  assert envs[0]._batch_substeps and not envs[1]._batch_substeps
  for env in envs:
    assert env.physics.model.opt.integrator == integrator


@pytest.mark.parametrize(
  'task',
  [('dclaw', 'pose_random'), ('dkitty', 'orient_random')],
  ids=['dclaw-pose_random', 'dkitty-orient_random'],
)
def test_extra_hook_added_after_reset_disables_batching(task):
  env = suite.load(*task, seed=0)
  timestep = env.reset()
  assert env._batch_substeps
  calls = []
  env.add_extra_hook(
    'after_substep', lambda physics, random_state: calls.append(1)
  )
  env.step(robel_spec.steady_policy(env)(timestep))
  assert len(calls) == env.task.physics_steps_per_control_step


def _divergences():
  def nan_qvel(physics):
    physics.data.qvel[0] = np.nan

  def huge_force(physics):
    physics.data.qfrc_applied[0] = 1e15

  return {'nan_qvel': nan_qvel, 'huge_qacc': huge_force}


@pytest.mark.slow
@pytest.mark.parametrize('hooked', [False, True], ids=['fast', 'hooked'])
@pytest.mark.parametrize('divergence', list(_divergences()))
@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_physics_divergence_raises(task, divergence, hooked):
  env = suite.load(*task, seed=0)
  if hooked:
    env.add_extra_hook('after_substep', _noop_hook)
  timestep = env.reset()
  policy = robel_spec.steady_policy(env)
  assert env._batch_substeps != hooked
  timestep = env.step(policy(timestep))
  _divergences()[divergence](env.physics)
  with pytest.raises(control.PhysicsError):
    env.step(policy(timestep))
  env.physics.data.qfrc_applied[:] = 0
  # The next episode runs normally.
  timestep = env.reset()
  assert timestep.first()
  assert env.step(policy(timestep)).mid()


@pytest.mark.parametrize('hooked', [False, True], ids=['fast', 'hooked'])
@pytest.mark.parametrize(
  'task',
  [('dclaw', 'pose_fixed'), ('dkitty', 'stand_fixed')],
  ids=['dclaw-pose_fixed', 'dkitty-stand_fixed'],
)
def test_physics_divergence_ends_the_episode_when_not_raising(
  task, hooked, caplog
):
  env = suite.load(
    *task, seed=0,
    environment_kwargs={'raise_exception_on_physics_error': False},
  )  # fmt: skip
  if hooked:
    env.add_extra_hook('after_substep', _noop_hook)
  timestep = env.reset()
  policy = robel_spec.steady_policy(env)
  assert env._batch_substeps != hooked
  timestep = env.step(policy(timestep))
  env.physics.data.qvel[3] = np.inf
  with caplog.at_level(logging.WARNING):
    timestep = env.step(policy(timestep))
  # Logged as composer logs it, on either path.
  assert 'Physics state is invalid' in caplog.text
  assert timestep.last()
  assert timestep.reward == 0.0 and timestep.discount == 0.0
  assert env.step(policy(timestep)).first()


@pytest.mark.slow
@pytest.mark.parametrize(
  'task',
  [('dclaw', 'turn_fixed'), ('dkitty', 'stand_random_dynamics')],
  ids=['dclaw-turn_fixed', 'dkitty-stand_random_dynamics'],
)
def test_model_is_compiled_once_and_physics_survives_the_first_reset(task):
  env = suite.load(*task, seed=0)
  physics = env.physics  # A weak proxy: dead if the model were recompiled.
  env.reset()
  env.step(np.zeros(env.action_spec().shape))
  assert physics.data.time > 0.0
  assert physics.model.nq == env.physics.model.nq
