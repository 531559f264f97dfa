"""Behaviour cloning: a tanh-squashed MLP fitted to demonstrated actions.

The network is the shape `policies.NumpyPolicy` runs (ReLU layers, a tanh
output), so the result is saved and evaluated like any trained actor. The
loss is the mean squared error between its actions and the demonstrated
ones, minimized with Adam on mini-batches (JAX, one CPU thread).
"""

from collections.abc import Callable, Sequence
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


def fit(
  data: demos.Transitions,
  hidden: Sequence[int],
  seed: int,
  epochs: int,
  batch_size: int,
  learning_rate: float,
  metadata: dict[str, Any],
  on_epoch: Callable[[int, policies.NumpyPolicy, float], None] | None = None,
  every: int = 50,
) -> policies.NumpyPolicy:
  """Fits a policy to `data`.

  Args:
    data: the demonstrations.
    hidden: hidden layer sizes.
    seed: seeds the initial weights and the batches.
    epochs: passes over the data.
    batch_size: transitions per gradient step.
    learning_rate: Adam's step size.
    metadata: the policy's metadata (task, observation keys, ...).
    on_epoch: called as on_epoch(epoch, policy, loss) every `every` epochs
      and after the last.
    every: see on_epoch.

  Returns:
    The fitted policy.
  """
  agents.single_thread()
  import jax  # noqa: PLC0415
  import jax.numpy as jnp  # noqa: PLC0415
  import optax  # noqa: PLC0415

  rng = np.random.default_rng(seed)
  observations = jnp.asarray(data.observations)
  targets = jnp.asarray(np.clip(data.actions, -1.0, 1.0))
  sizes = [observations.shape[1], *hidden, targets.shape[1]]
  params = [tuple(map(jnp.asarray, layer)) for layer in _init(rng, sizes)]
  optimizer = optax.adam(learning_rate)
  state = optimizer.init(params)

  def forward(params, x):
    for weight, bias in params[:-1]:
      x = jax.nn.relu(x @ weight.T + bias)
    weight, bias = params[-1]
    return jnp.tanh(x @ weight.T + bias)

  def loss_fn(params, x, y):
    return jnp.mean(jnp.sum((forward(params, x) - y) ** 2, axis=-1))

  @jax.jit
  def step(params, state, x, y):
    loss, grads = jax.value_and_grad(loss_fn)(params, x, y)
    updates, state = optimizer.update(grads, state, params)
    return optax.apply_updates(params, updates), state, loss

  def as_policy(params):
    return policies.NumpyPolicy(
      [np.asarray(w) for w, _ in params],
      [np.asarray(b) for _, b in params],
      'relu',
      'tanh',
      metadata,
    )

  n = len(data)
  batch = min(batch_size, n)
  loss = float('nan')
  for epoch in range(1, epochs + 1):
    order = rng.permutation(n)
    losses = []
    for start in range(0, n - batch + 1, batch):
      index = order[start : start + batch]
      params, state, value = step(
        params, state, observations[index], targets[index]
      )
      losses.append(value)
    loss = float(np.mean(jax.device_get(losses)))
    if on_epoch is not None and (epoch % every == 0 or epoch == epochs):
      on_epoch(epoch, as_policy(params), loss)
  return as_policy(params)
