"""Behaviour cloning: a tanh-squashed MLP fitted to demonstrated actions.

The network is the shape `policies.NumpyPolicy` runs (ReLU layers, a tanh
output), so the result is saved and evaluated like any trained actor. The
loss is the mean squared error between its actions and the demonstrated
ones, minimized with Adam on mini-batches (JAX, one CPU thread).
"""

from collections.abc import Callable, Sequence
import dataclasses
from typing import Any

import numpy as np

from robel_dm import policies
from robel_dm.learning import agents, demos


def _init(rng: np.random.Generator, sizes: Sequence[int]):
  """He-uniform weights (out, in) and zero biases."""
  layers = []
  for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
    bound = np.sqrt(6.0 / fan_in)
    layers.append(
      (
        rng.uniform(-bound, bound, (fan_out, fan_in)).astype(np.float32),
        np.zeros(fan_out, np.float32),
      )
    )
  return layers


@dataclasses.dataclass(frozen=True)
class FitConfig:
  """How `fit_policy` fits a policy to demonstrations.

  Attributes:
    hidden: hidden layer sizes.
    seed: seeds the initial weights and the batches.
    epochs: passes over the data.
    batch_size: transitions per gradient step.
    learning_rate: Adam's step size.
    every: `fit_policy` reports the policy every this many epochs (and
      after the last).
  """

  hidden: Sequence[int]
  seed: int
  epochs: int
  batch_size: int
  learning_rate: float
  every: int = 50


# Reports a fit's progress: on_epoch(epoch, policy, loss).
EpochCallback = Callable[[int, policies.NumpyPolicy, float], None]


def fit_policy(
  data: demos.Transitions,
  config: FitConfig,
  metadata: dict[str, Any],
  on_epoch: EpochCallback | None = None,
) -> policies.NumpyPolicy:
  """Fits a policy to `data`.

  Args:
    data: the demonstrations.
    config: the network and the training options.
    metadata: the policy's metadata (task, observation keys, ...).
    on_epoch: called as on_epoch(epoch, policy, loss) every `config.every`
      epochs and after the last.

  Returns:
    The fitted policy.
  """
  agents.single_thread()
  import jax  # noqa: PLC0415
  import jax.numpy as jnp  # noqa: PLC0415
  import optax  # noqa: PLC0415

  rng = np.random.default_rng(config.seed)
  observations = jnp.asarray(data.observations)
  targets = jnp.asarray(np.clip(data.actions, -1.0, 1.0))
  sizes = [observations.shape[1], *config.hidden, targets.shape[1]]
  params = [tuple(map(jnp.asarray, layer)) for layer in _init(rng, sizes)]
  optimizer = optax.adam(config.learning_rate)
  state = optimizer.init(params)
  step = _training_step(optimizer)
  n = len(data)
  batch = min(config.batch_size, n)
  loss = float('nan')
  for epoch in range(1, config.epochs + 1):
    order = rng.permutation(n)
    losses = []
    for start in range(0, n - batch + 1, batch):
      index = order[start : start + batch]
      params, state, value = step(
        params, state, observations[index], targets[index]
      )
      losses.append(value)
    loss = float(np.mean(jax.device_get(losses)))
    last = epoch == config.epochs
    if on_epoch is not None and (epoch % config.every == 0 or last):
      on_epoch(epoch, _as_policy(params, metadata), loss)
  return _as_policy(params, metadata)


def _forward(params, x):
  """The network's actions for observations `x`."""
  import jax  # noqa: PLC0415
  import jax.numpy as jnp  # noqa: PLC0415

  for weight, bias in params[:-1]:
    x = jax.nn.relu(x @ weight.T + bias)
  weight, bias = params[-1]
  return jnp.tanh(x @ weight.T + bias)


def _training_step(optimizer):
  """One jitted gradient step of the mean squared action error:
  step(params, state, x, y) -> (params, state, loss)."""
  import jax  # noqa: PLC0415
  import jax.numpy as jnp  # noqa: PLC0415
  import optax  # noqa: PLC0415

  def loss_fn(params, x, y):
    return jnp.mean(jnp.sum((_forward(params, x) - y) ** 2, axis=-1))

  @jax.jit
  def step(params, state, x, y):
    loss, grads = jax.value_and_grad(loss_fn)(params, x, y)
    updates, state = optimizer.update(grads, state, params)
    return optax.apply_updates(params, updates), state, loss

  return step


def _as_policy(params, metadata: dict[str, Any]) -> policies.NumpyPolicy:
  """The network as a numpy policy."""
  return policies.NumpyPolicy(
    [np.asarray(w) for w, _ in params],
    [np.asarray(b) for _, b in params],
    'relu',
    'tanh',
    metadata,
  )
