"""SAC as `train --algo=sac` runs it: sbx's jitted updates, numpy around
them.

sbx (Stable-Baselines3's API on JAX) makes SAC's gradient updates in one
jitted call. Around them, SB3's loop spends per env step about a
millisecond on two things this subclass does in numpy instead, with the
same mathematics:

- the exploration action: a jitted JAX call per step in sbx; here the
  actor in numpy (`actor.StochasticActor`), its weights read once per
  update;
- the replay sample: copied through torch tensors in SB3; here indexed
  straight out of the buffer's arrays.

Both random streams (exploration noise, replay indices) are generators of
the model, saved with it, so a resumed run continues them.

With a `SafetyConstraint`, the model maximizes the task reward while
holding ROBEL's safety violations per episode under a budget (a
Lagrangian relaxation): the replay buffer keeps each transition's
violations beside its reward, a batch's rewards are the task's minus the
current multiplier times those violations, and the multiplier rises while
training episodes exceed the budget and falls while they stay under it.
Relabelling at sampling time means every stored transition is priced at
the current multiplier, not at the one it was collected under.
"""

import functools

import numpy as np

from robel_dm.learning import actor, extra
from robel_dm.learning.safety import SafetyConstraint, step_violations

try:
  import flax.linen as nn
  import jax.numpy as jnp
  import sbx
  from sbx.common.distributions import TanhTransformedDistribution
  from sbx.common.policies import SquashedGaussianActor
  from sbx.common.type_aliases import ReplayBufferSamplesNp
  from sbx.sac.policies import SACPolicy
  from tensorflow_probability.substrates import jax as tfp
except ImportError as error:  # The optional learn extra.
  raise extra.missing(error) from error


class PrefixActor(SquashedGaussianActor):
  """sbx's actor, seeing only the first `observed` observation entries.

  The critics see the whole observation, which ends with what only a
  simulation knows (an asymmetric actor-critic); the actor's first layer
  takes the robot's share, so the trained actor runs on a robot.
  """

  observed: int = 0

  @nn.compact
  def __call__(self, x: jnp.ndarray):
    x = x[..., : self.observed]
    for n_units in self.net_arch:
      x = self.activation_fn(nn.Dense(n_units)(x))
    mean = nn.Dense(self.action_dim)(x)
    log_std = jnp.clip(
      nn.Dense(self.action_dim)(x), self.log_std_min, self.log_std_max
    )
    return TanhTransformedDistribution(
      tfp.distributions.MultivariateNormalDiag(
        loc=mean, scale_diag=jnp.exp(log_std)
      )
    )


class NumpyActingPolicy(SACPolicy):
  """sbx's SAC policy, acting with its actor in numpy."""

  # A `PrefixActor` acts on the first `observed` entries; None: on all
  # (also the value of a policy saved before this attribute existed).
  observed: int | None = None

  def __init__(self, *args, **kwargs):
    super().__init__(*args, **kwargs)
    # Seeded by `SAC.set_random_seed`.
    self.rng = np.random.default_rng(0)
    self._actor: actor.StochasticActor | None = None
    self._actor_of = None
    keywords = getattr(self.actor_class, 'keywords', {})
    self.observed = keywords.get('observed')

  def numpy_actor(self) -> actor.StochasticActor:
    """The current actor in numpy (read again after each update)."""
    if self._actor_of is not self.actor_state:
      self._actor = actor.StochasticActor(
        actor.layers_of(self.actor_state.params)
      )
      self._actor_of = self.actor_state
    return self._actor

  def _predict(self, observation, deterministic: bool = False):
    observation = np.asarray(observation, np.float32)
    if self.observed is not None:
      observation = observation[..., : self.observed]
    if deterministic:
      return self.numpy_actor().mean(observation)
    return self.numpy_actor().sample(observation, self.rng)

  def __getstate__(self):
    state = self.__dict__.copy()
    state['_actor'] = state['_actor_of'] = None  # Rebuilt when needed.
    return state


class SAC(sbx.SAC):
  """sbx's SAC, acting and sampling its replay buffer in numpy."""

  policy_aliases = {'MlpPolicy': NumpyActingPolicy}  # noqa: RUF012
  # Set after building or loading to learn under a safety budget.
  safety: SafetyConstraint | None = None

  @staticmethod
  def prefix_actor(observed: int):
    """The `actor_class` of a policy whose actor sees the first `observed`
    observation entries (`PrefixActor`)."""
    return functools.partial(PrefixActor, observed=observed)

  def set_random_seed(self, seed: int | None) -> None:
    super().set_random_seed(seed)
    # Exploration noise and replay indices: streams of their own.
    streams = np.random.SeedSequence(seed).spawn(2)
    self.replay_rng = np.random.default_rng(streams[0])
    self._exploration_rng = np.random.default_rng(streams[1])

  def _setup_model(self) -> None:
    # SB3's `load` sets the saved attributes (the policy among them), then
    # calls this, which reseeds: a loaded model keeps its saved streams.
    loaded = getattr(self, 'policy', None) is not None
    saved = (self.key, getattr(self, 'replay_rng', None)) if loaded else None
    super()._setup_model()
    if loaded:
      self.key = saved[0]
      self.replay_rng = saved[1] or self.replay_rng
    else:
      self.policy.rng = self._exploration_rng
    del self._exploration_rng

  def start_over(self, seed: int, buffer_size: int) -> None:
    """Keeps the networks and the entropy coefficient, and starts a new run
    from them: counters at 0, random streams from `seed`, an empty replay
    buffer of `buffer_size` transitions, no safety budget (the new run's
    own, if any, is set after)."""
    self.num_timesteps = self._episode_num = self._n_updates = 0
    self.safety = None
    self.set_random_seed(seed)
    self.policy.rng = self._exploration_rng
    del self._exploration_rng
    self.replay_buffer = type(self.replay_buffer)(
      max(buffer_size, 1),
      self.observation_space,
      self.action_space,
      device='cpu',
      n_envs=self.n_envs,
    )

  def sample_replay(self, count: int) -> ReplayBufferSamplesNp:
    """`count` transitions drawn uniformly (with replacement) from the
    buffer, as SB3's `ReplayBuffer.sample` draws them."""
    buffer = self.replay_buffer
    held = buffer.buffer_size if buffer.full else buffer.pos
    rows = self.replay_rng.integers(0, held, size=count)
    envs = self.replay_rng.integers(0, buffer.n_envs, size=count)
    # A transition cut by the time limit is not terminal: it bootstraps.
    terminal = buffer.dones[rows, envs] * (1.0 - buffer.timeouts[rows, envs])
    rewards = buffer.rewards[rows, envs]
    if self.safety is not None and self.safety.multiplier:
      rewards = (
        rewards - self.safety.multiplier * self._violations()[rows, envs]
      )
    return ReplayBufferSamplesNp(
      buffer.observations[rows, envs],
      buffer.actions[rows, envs],
      buffer.next_observations[rows, envs],
      terminal.astype(np.float32),
      rewards.astype(np.float32),
      np.full(count, self.gamma, np.float32),
    )

  def _violations(self) -> np.ndarray:
    """The safety violations of every stored transition, kept with the
    buffer (so that they are saved and restored with it)."""
    buffer = self.replay_buffer
    if getattr(buffer, 'violations', None) is None:
      buffer.violations = np.zeros_like(buffer.rewards)
    return buffer.violations

  def _store_transition(
    self, replay_buffer, buffer_action, new_obs, reward, dones, infos
  ) -> None:
    if self.safety is not None:
      violations = step_violations(infos)
      # Stored at the row the buffer is about to fill.
      self._violations()[replay_buffer.pos] = violations
      self.safety.observe(violations, np.asarray(dones, bool))
    super()._store_transition(
      replay_buffer, buffer_action, new_obs, reward, dones, infos
    )

  def train(self, gradient_steps: int, batch_size: int) -> None:
    """`gradient_steps` updates on batches of `batch_size`, in one call."""
    self._maybe_reset_params()
    data = self.sample_replay(batch_size * gradient_steps)
    learning_rate = self.lr_schedule(self._current_progress_remaining)
    self._update_learning_rate(
      self.policy.actor_state.opt_state,
      learning_rate=learning_rate,
      name='learning_rate_actor',
    )
    self._update_learning_rate(
      self.policy.qf_state.opt_state,
      learning_rate=self.initial_qf_learning_rate or learning_rate,
      name='learning_rate_critic',
    )
    (
      self.policy.qf_state,
      self.policy.actor_state,
      self.ent_coef_state,
      self.key,
      losses,
    ) = self._train(
      self.tau,
      self.target_entropy,
      gradient_steps,
      data,
      self.policy_delay,
      (self._n_updates + 1) % self.policy_delay,
      self.policy.qf_state,
      self.policy.actor_state,
      self.ent_coef_state,
      self.key,
    )
    self._n_updates += gradient_steps
    actor_loss, critic_loss, ent_coef_loss, ent_coef = losses
    self.logger.record(
      'train/n_updates', self._n_updates, exclude='tensorboard'
    )
    self.logger.record('train/actor_loss', float(actor_loss))
    self.logger.record('train/critic_loss', float(critic_loss))
    self.logger.record('train/ent_coef_loss', float(ent_coef_loss))
    self.logger.record('train/ent_coef', float(ent_coef))
    if self.safety is not None:
      self.logger.record('train/safety_multiplier', self.safety.multiplier)
