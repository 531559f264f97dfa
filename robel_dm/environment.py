"""A composer.Environment that steps physics in one batch per control step.

composer's step loop calls three hook dispatchers, `physics.step()` and the
observation updater once per physics substep (about 4 us each). ROBEL runs 20
or 40 substeps per control step, so that loop costs 15-30% of an `env.step`.
When no substep hook is defined and every observable samples only the final
substep (composer's "fast path" with a buffer of 1), the intermediate substeps
are invisible to the task and the agent, and one `physics.step(n)` gives
bit-identical physics. In the same situation observation buffering is a no-op,
so observables are evaluated once per control step without the buffers. In any
other configuration composer's own loop and updater run unchanged.

This module is robel_dm's only adapter to dm_control internals: composer has
no public hook for the above, so it reads or overrides the private names below
(dm-control is pinned, and the tests pin the behaviour: the batched loop is
bit-identical to composer's). No other robel_dm module uses them.

composer.Environment
  _recompile_physics: overridden to build the physics with `physics_factory`
    (a robot's physics on hardware).
  _make_observation_updater: overridden to build the lean updater.
  _mjcf_never_compiled, _recompile_mjcf_every_episode,
    _hooks._initialize_episode_mjcf: cleared / read to skip composer's second
    compile at the first reset when no MJCF hook needs it.
  _hooks._before_step, _after_step, _before_substep, _after_substep
    (entity_hooks, extra_hooks): read to know whether substeps are observed
    and whether the task's hooks can be called directly.
  _task, _physics, _physics_proxy, _random_state, _n_sub_steps, _time_limit,
    _reset_next_step, _raise_exception_on_physics_error,
    _observation_updater, _legacy_step, _delayed_observation_padding,
    _strip_singleton_obs_buffer_dim: the state composer's own `step` and
    `_recompile_physics` use, which their replacements here use the same way.
mjcf.Physics
  _contexts: read by `existing_render_contexts` (the public `contexts`
    creates a GL context, which crashes on a headless machine).
observation.Updater
  _enabled_list, _enabled_structure, _is_nested, _strip_singleton_buffer_dim:
    read to decide whether the lean path applies and to name its outputs.
  _physics_steps_per_control_step, _step_counter: the updater's clock, which
    the batched step advances without sampling.
"""

import collections
from collections.abc import Callable

from absl import logging
from dm_control import composer, mjcf
from dm_control.composer.observation import observable, updater
from dm_control.rl import control
import dm_env
import numpy as np

_SUBSTEP_HOOKS = ('before_substep', 'after_substep')

PhysicsFactory = Callable[[mjcf.RootElement], mjcf.Physics]


def existing_render_contexts(physics):
  """The physics' rendering contexts if a renderer made them, else None
  (never creates one)."""
  return physics._contexts  # noqa: SLF001


class CachedArray(observable.Observable):
  """An observable of an array its owner (a task) keeps up to date.

  Each reading is a fresh copy (`ndarray.copy`, called without a Python
  frame in between), so readings never share memory with the owner or with
  each other, and the lean updater below needs no second copy.
  """

  def __init__(self, value: np.ndarray):
    super().__init__(
      update_interval=1,
      buffer_size=None,
      delay=None,
      aggregator=None,
      corruptor=None,
    )
    self.value = value

  def _callable(self, physics):
    del physics
    return self.value.copy


def _fresh_copy(enabled) -> bool:
  """Whether an observable's readings are new arrays of its spec's dtype."""
  observable_ = enabled.observable
  return (
    isinstance(observable_, CachedArray)
    and observable_.corruptor is None
    and observable_.value.dtype == enabled.buffer.dtype
  )


class _Updater(updater.Updater):
  """Observation updater with a lean path for last-substep-only observables."""

  def reset(self, physics, random_state):
    super().reset(physics, random_state)
    enabled = list(self._enabled_list)
    self._last_substep_only = all(
      e.update_interval == 1 and e.delay == 0 and e.buffer_size == 1
      for e in enabled
    )
    # Lean path: no buffers at all; one evaluation per observable and step.
    self._lean = (
      self._last_substep_only
      and not self._is_nested
      and self._strip_singleton_buffer_dim
      and all(e.observable.aggregator is None for e in enabled)
    )
    if self._lean:
      self._names = tuple(self._enabled_structure)
      # A reading that is already a fresh array of the right dtype (the
      # tasks' cached arrays without a corruptor) needs no second copy.
      self._sources = tuple(
        (
          e.observation_callable,
          None if _fresh_copy(e) else e.buffer.dtype,
        )
        for e in enabled
      )
      self._latest = [e.buffer.read(0) for e in enabled]
      self._handed_out = False

  def samples_last_substep_only(self) -> bool:
    return self._last_substep_only

  def skip_substeps(self, count: int) -> None:
    # Fast-path observables are scheduled on the last substep only, so the
    # skipped updates would have sampled nothing: advance the clock alone.
    self._step_counter += count

  def prepare_for_next_control_step(self):
    if not self._lean:
      super().prepare_for_next_control_step()

  def update(self):
    if not self._lean:
      super().update()
      return
    self._step_counter += 1
    if self._step_counter % self._physics_steps_per_control_step == 0:
      self._latest = [
        get() if dtype is None else np.array(get(), dtype)
        for get, dtype in self._sources
      ]
      self._handed_out = False

  def get_observation(self):
    if not self._lean:
      return super().get_observation()
    values = self._latest
    if self._handed_out:  # Never hand the same arrays out twice.
      values = [value.copy() for value in values]
    self._handed_out = True
    return collections.OrderedDict(zip(self._names, values, strict=True))


class Environment(composer.Environment):
  """composer.Environment with robel_dm's defaults and batched substeps.

  Defaults differ from composer's: the MJCF is compiled once (per-episode
  variation happens on the compiled model), and singleton buffer dimensions are
  stripped so observations have their natural shapes.
  """

  def __init__(
    self,
    task: composer.Task,
    physics_factory: PhysicsFactory | None = None,
    control_delay: float = 0.0,
    calibration=None,
    **kwargs,
  ):
    """Initializes the environment.

    Args:
      task: the task.
      physics_factory: builds the physics of a compiled model;
        `mjcf.Physics.from_mjcf_model` (simulation) by default.
      control_delay: simulated delay between an action and the actuators
        acting on it, s (a calibrated servo delay; see `robel_dm.calibration`).
        The previous targets hold for this long (rounded to whole physics
        steps) into each control step.
      calibration: the `robel_dm.calibration.Calibration` the model was
        built with, or None (kept for what reads the simulation, e.g. a
        virtual bus applying its sensor noise).
      **kwargs: `composer.Environment` arguments.

    Raises:
      ValueError: if `control_delay` is negative or not below one control
        step.
    """
    kwargs.setdefault('recompile_mjcf_every_episode', False)
    kwargs.setdefault('strip_singleton_obs_buffer_dim', True)
    self._batch_substeps = False
    self._closed = False
    self._calibration = calibration
    substeps = task.physics_steps_per_control_step
    delay = control_delay / task.physics_timestep
    self._delay_substeps = round(delay) if 0 <= delay < substeps else -1
    if not 0 <= self._delay_substeps < substeps:  # Also NaN.
      # A calibration file's delay is named with the file.
      source = '' if calibration is None else f'{calibration.source}: '
      raise ValueError(
        f'{source}control_delay {control_delay} s is not below the control '
        f'step of {type(task).__name__} ({task.control_timestep} s) or is '
        'negative'
      )
    self._physics_factory = physics_factory or mjcf.Physics.from_mjcf_model
    super().__init__(task, **kwargs)
    # The constructor has compiled the model. composer compiles it again at
    # the first reset, to run `initialize_episode_mjcf` hooks first; when
    # there are none and the model is never recompiled, skip that second
    # compile so `env.physics` stays valid from construction on.
    if not (
      self._recompile_mjcf_every_episode
      or type(task).initialize_episode_mjcf
      is not composer.Task.initialize_episode_mjcf
      or self._hooks._initialize_episode_mjcf.entity_hooks
    ):
      self._mjcf_never_compiled = False

  def _recompile_physics(self):
    physics = getattr(self, '_physics', None)
    if physics:
      physics.free()
    self._physics = self._physics_factory(self._task.root_entity.mjcf_model)
    self._physics.legacy_step = self._legacy_step

  def _make_observation_updater(self):
    pad = (
      self._delayed_observation_padding
      == composer.ObservationPadding.INITIAL_VALUE
    )
    return _Updater(
      self._task.observables,
      self._task.physics_steps_per_control_step,
      self._strip_singleton_obs_buffer_dim,
      pad,
    )

  def _substeps_are_unobserved(self) -> bool:
    task_type = type(self._task)
    for hook_name in _SUBSTEP_HOOKS:
      if getattr(task_type, hook_name) is not getattr(composer.Task, hook_name):
        return False
      hook = getattr(self._hooks, '_' + hook_name)
      if hook.entity_hooks or hook.extra_hooks:
        return False
    return self._observation_updater.samples_last_substep_only()

  @property
  def calibration(self):
    """The calibration the model was built with, or None."""
    return self._calibration

  @property
  def control_delay(self) -> float:
    """The simulated action delay, s (whole physics steps)."""
    return self._delay_substeps * self._task.physics_timestep

  def _prepare_batching(self) -> None:
    self._batch_substeps = self._substeps_are_unobserved()
    if self._delay_substeps and not self._batch_substeps:
      raise ValueError(
        'a control_delay needs a task whose substeps are unobserved'
      )
    if self._delay_substeps:
      ctrl = self._physics.data.ctrl
      self._held_ctrl, self._next_ctrl = ctrl.copy(), ctrl.copy()
    # With no entity or extra step hooks, call the task's hooks directly.
    self._task_hooks_only = not any(
      hook.entity_hooks or hook.extra_hooks
      for hook in (self._hooks._before_step, self._hooks._after_step)
    )
    self._data_ptr = self._physics.data.ptr  # The raw MjData (fast time).

  def add_extra_hook(self, hook_name, hook_callable):
    super().add_extra_hook(hook_name, hook_callable)
    self._prepare_batching()

  def close(self) -> None:
    """Frees the physics; closing again does nothing."""
    if self._closed:
      return
    self._closed = True
    super().close()

  def _check_open(self) -> None:
    if self._closed:
      raise RuntimeError(
        'the environment is closed; load a new one to continue'
      )

  def reset(self) -> dm_env.TimeStep:
    self._check_open()
    timestep = super().reset()
    self._prepare_batching()
    return timestep

  def step(self, action) -> dm_env.TimeStep:
    if self._closed:
      self._check_open()
    if not self._batch_substeps or self._reset_next_step:
      return super().step(action)

    physics, random_state = self._physics_proxy, self._random_state
    if self._delay_substeps:
      np.copyto(self._held_ctrl, self._physics.data.ctrl)
    if self._task_hooks_only:
      self._task.before_step(physics, action, random_state)
    else:
      self._hooks.before_step(physics, action, random_state)
    self._observation_updater.prepare_for_next_control_step()
    try:
      # The legacy step of all substeps at once (on hardware: one exchange
      # with the motors); it raises on MuJoCo warnings, as composer's does.
      if self._delay_substeps:
        self._step_delayed()
      else:
        self._physics.step(self._n_sub_steps)
      physics_is_divergent = False
    except control.PhysicsError as error:
      if self._raise_exception_on_physics_error:
        raise
      logging.warning(error)
      physics_is_divergent = True
    self._observation_updater.skip_substeps(self._n_sub_steps - 1)
    if self._task_hooks_only:
      self._task.after_step(physics, random_state)
    else:
      self._hooks.after_step(physics, random_state)
    self._observation_updater.update()

    if physics_is_divergent:
      reward, discount, terminating = 0.0, 0.0, True
    else:
      reward = self._task.get_reward(physics)
      discount = self._task.get_discount(physics)
      terminating = (
        self._task.should_terminate_episode(physics)
        or self._data_ptr.time >= self._time_limit
      )
    observation = self._observation_updater.get_observation()
    if terminating:
      self._reset_next_step = True
      return dm_env.TimeStep(
        dm_env.StepType.LAST, reward, discount, observation
      )
    return dm_env.TimeStep(dm_env.StepType.MID, reward, discount, observation)

  def _step_delayed(self) -> None:
    """The control step's substeps with the previous targets held for the
    first `_delay_substeps`."""
    ctrl = self._physics.data.ctrl
    np.copyto(self._next_ctrl, ctrl)
    np.copyto(ctrl, self._held_ctrl)
    self._physics.step(self._delay_substeps)
    np.copyto(ctrl, self._next_ctrl)
    self._physics.step(self._n_sub_steps - self._delay_substeps)
