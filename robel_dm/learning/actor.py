"""SAC's actor in numpy: what acts on a robot and in training rollouts.

An sbx SAC actor is a ReLU network whose last two dense layers give the
mean and the log-std of a Gaussian; the action is the tanh of a sample
(the deterministic action: the tanh of the mean). Acting in numpy costs
tens of microseconds per step where a jitted JAX call costs most of a
millisecond, and needs no JAX in the process that holds the robot.
"""

import numpy as np

from robel_dm import policies

# sbx clips the log-std to [-20, 2].
LOG_STD_RANGE = (-20.0, 2.0)


def layers_of(params) -> list[tuple[np.ndarray, np.ndarray]]:
  """An sbx SAC actor's dense layers, from its parameters (the
  `actor_state.params` pytree), as (weight (out, in), bias) arrays: the
  hidden layers, then the mean, then the log-std."""
  dense = params['params']
  names = sorted(
    (name for name in dense if name.startswith('Dense_')),
    key=lambda name: int(name.split('_')[1]),
  )
  return [
    (np.asarray(dense[name]['kernel']).T, np.asarray(dense[name]['bias']))
    for name in names
  ]


class StochasticActor:
  """SAC's actor in numpy, for one observation (1-D) or a batch (2-D)."""

  def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]]):
    *self.hidden, self.mean_layer, self.log_std_layer = layers

  def _features(self, observation: np.ndarray) -> np.ndarray:
    x = observation
    for weight, bias in self.hidden:
      x = np.maximum(x @ weight.T + bias, 0.0)
    return x

  def mean(self, observation: np.ndarray) -> np.ndarray:
    """The deterministic action: tanh of the mean."""
    weight, bias = self.mean_layer
    return np.tanh(self._features(observation) @ weight.T + bias)

  def sample(
    self, observation: np.ndarray, rng: np.random.Generator
  ) -> np.ndarray:
    """An exploration action: tanh of a sample of the Gaussian."""
    x = self._features(observation)
    mean = x @ self.mean_layer[0].T + self.mean_layer[1]
    log_std = np.clip(
      x @ self.log_std_layer[0].T + self.log_std_layer[1], *LOG_STD_RANGE
    )
    noise = rng.standard_normal(mean.shape).astype(mean.dtype)
    return np.tanh(mean + np.exp(log_std) * noise)

  def numpy_policy(self, metadata: dict) -> policies.NumpyPolicy:
    """The deterministic actor as a saved-policy object."""
    layers = [*self.hidden, self.mean_layer]
    return policies.NumpyPolicy(
      [w for w, _ in layers], [b for _, b in layers], 'relu', 'tanh', metadata
    )
