"""The replay buffer of an off-policy agent (SB3's `ReplayBuffer`, one
environment): transitions stored in bulk, and room made for more."""

import numpy as np

from robel_dm.learning import demos


def store(buffer, data: demos.Transitions) -> None:
  """Appends transitions to `buffer`; when it is full the oldest go first,
  as SB3's own `add` does.

  Their safety violations, when known, go to `buffer.violations` (made,
  zeros like the rewards, if the buffer has none yet; what a safety budget
  prices, see `robel_dm.learning.sac`); unknown ones count 0 there.
  """
  rows = (buffer.pos + np.arange(len(data))) % buffer.buffer_size
  buffer.observations[rows, 0] = data.observations
  buffer.next_observations[rows, 0] = data.next_observations
  buffer.actions[rows, 0] = data.actions
  buffer.rewards[rows, 0] = data.rewards
  buffer.dones[rows, 0] = data.terminals
  if data.violations is not None:
    if getattr(buffer, 'violations', None) is None:
      buffer.violations = np.zeros_like(buffer.rewards)
    buffer.violations[rows, 0] = data.violations
  elif getattr(buffer, 'violations', None) is not None:
    buffer.violations[rows, 0] = 0.0  # Not an overwritten row's.
  end = buffer.pos + len(data)
  buffer.full = buffer.full or end >= buffer.buffer_size
  buffer.pos = end % buffer.buffer_size


def grow(model, size: int) -> None:
  """Gives a loaded replay buffer room for `size` transitions in all,
  keeping every transition it holds (in order)."""
  buffer = model.replay_buffer
  if buffer.buffer_size >= size:
    return
  held = buffer.buffer_size if buffer.full else buffer.pos
  start = buffer.pos if buffer.full else 0
  order = (np.arange(held) + start) % buffer.buffer_size
  grown = type(buffer)(
    size,
    buffer.observation_space,
    buffer.action_space,
    device='cpu',
    n_envs=buffer.n_envs,
  )
  for name in (
    'observations',
    'next_observations',
    'actions',
    'rewards',
    'dones',
    'timeouts',
  ):
    getattr(grown, name)[:held] = getattr(buffer, name)[order]
  violations = getattr(buffer, 'violations', None)  # Under a safety budget.
  if violations is not None:
    grown.violations = np.zeros_like(grown.rewards)
    grown.violations[:held] = violations[order]
  grown.pos, grown.full = held, False
  model.replay_buffer = grown
