"""What a training run reports as it goes: TensorBoard event files in the
run directory and progress lines on the terminal.

TensorBoard (`tensorboard --logdir RUN_DIR`) gets, under the same tags for
every agent:

  eval/success_rate, eval/mean_score, eval/mean_return,
  eval/violations_<kind>   at each evaluation (x: env steps; epochs for bc)
  train/<name>             what the agent logs as it learns (SB3's and
                           sbx's names: actor_loss, critic_loss, ent_coef,
                           policy_gradient_loss, ...; bc: loss)
  speed/env_steps_per_second
  config                   the run's settings (text, once)

and a run on a robot, at the end of every episode (x: robot steps):

  train/<name>             the learner's latest values (as above)
  train/safety_multiplier  with --safety_budget: the price of one
                           violation, the latest the learner sent (it
                           moves at every training episode's end)
  robot/jitter_p50_ms, robot/jitter_p99_ms, robot/late_steps
                           the episode's control timing
  robot/violations_<kind>  the episode's safety violations
  robot/return, robot/success
                           the episode's (training and evaluation alike)
  robot/faults, robot/early_ends, robot/resets
                           so far in the run
  robot/updates_per_step   the learner's updates per step since learning
                           started
  robot/updates_per_second since the previous episode
  robot/actor_age_s        how old the actor weights acting were
  robot/seconds            the robot's time so far

Writing needs the `tensorboardX` package (in the `learn` extra); without it
a run says so in one line and trains as before. Between evaluations a
progress line is printed at most every `HEARTBEAT_SECONDS`, so a long
evaluation interval does not look like a hang.
"""

from collections.abc import Callable
import json
import pathlib
import time
from typing import Any

TENSORBOARD_DIR = 'tensorboard'
HEARTBEAT_SECONDS = 15.0


class Telemetry:
  """One run's TensorBoard writer and progress lines."""

  def __init__(
    self,
    output: pathlib.Path,
    name: str,
    config: dict[str, Any],
    budget: int,
    log: Callable[[str], None],
  ):
    """Opens the event file (if tensorboardX is installed).

    Args:
      output: the run directory (events go to its `tensorboard/`).
      name: how progress lines name the run.
      config: the run's settings, recorded once.
      budget: the run's env steps, for the progress lines.
      log: where progress lines go.
    """
    self._name, self._budget, self._log = name, budget, log
    self._last_line = time.monotonic()
    self._start: tuple[float, int] | None = None
    try:
      from tensorboardX import SummaryWriter  # noqa: PLC0415
    except ImportError:
      self._writer = None
      log(
        'TensorBoard logs are off: pip install tensorboardX (in the learn '
        'extra) to write them'
      )
      return
    self._writer = SummaryWriter(str(output / TENSORBOARD_DIR))
    self._writer.add_text(
      'config', f'```\n{json.dumps(config, indent=1)}\n```', 0
    )
    self._writer.flush()

  def evaluation(self, row: dict[str, Any]) -> None:
    """An evaluation's metrics (a row of the evaluation log)."""
    self._last_line = time.monotonic()
    if self._writer is None:
      return
    step = row.get('epoch', row['env_steps'])
    for key in ('success_rate', 'mean_score', 'mean_return'):
      self._writer.add_scalar(f'eval/{key}', row[key], step)
    for kind, value in row['safety'].items():
      self._writer.add_scalar(f'eval/violations_{kind}', value, step)
    if 'loss' in row:
      self._writer.add_scalar('train/loss', row['loss'], step)
    self._writer.flush()

  def training(self, values: dict[str, Any], steps: int) -> None:
    """What the agent logged while learning, at `steps` env steps; prints a
    progress line if none was printed for `HEARTBEAT_SECONDS`."""
    now = time.monotonic()
    if self._start is None:
      self._start = (now, steps)
    elapsed = now - self._start[0]
    rate = (steps - self._start[1]) / elapsed if elapsed > 0 else 0.0
    if self._writer is not None:
      for key, value in values.items():
        if key.startswith('train/') and isinstance(value, int | float):
          self._writer.add_scalar(key, value, steps)
      if rate:
        self._writer.add_scalar('speed/env_steps_per_second', rate, steps)
    if now - self._last_line >= HEARTBEAT_SECONDS:
      self._last_line = now
      left = (self._budget - steps) / rate / 60 if rate else float('nan')
      self._log(
        f'{self._name}: {steps} of {self._budget} steps, {rate:.0f} steps/s, '
        f'about {left:.1f} min left'
      )

  def scalars(self, values: dict[str, float], step: int) -> None:
    """Scalars under the tags given (e.g. a robot run's `robot/...`), at
    `step` env steps."""
    if self._writer is None:
      return
    for tag, value in values.items():
      self._writer.add_scalar(tag, value, step)
    self._writer.flush()

  def close(self) -> None:
    if self._writer is not None:
      self._writer.close()
      self._writer = None


def agent_log_output(telemetry: Telemetry, steps: Callable[[], int]):
  """An SB3 logger output that hands each dump of the agent's values, at
  `steps()` env steps, to `telemetry.training` (SB3 dumps every few
  episodes off-policy, every rollout on-policy)."""
  from stable_baselines3.common import logger  # noqa: PLC0415

  class _Output(logger.KVWriter):
    def write(self, key_values, key_excluded, step: int = 0) -> None:
      del key_excluded, step  # SB3's step counts dumps, not env steps.
      telemetry.training(dict(key_values), steps())

    def close(self) -> None:
      pass

  return _Output()
