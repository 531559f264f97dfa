"""How well the hardware control loop keeps its period.

Every control step sends its goals, waits for its tick, then reads the
motors. `ControlTiming` keeps, per step, the control period actually
achieved (the time between two successive wake-ups at a tick) and how late
the step came to its tick (counted after its goals were sent, so a slow
write shows as lateness). A step is *late* when the code before it (the
policy, a learner competing for the CPU, a slow bus) ran past its tick by
more than `LATE_TOLERANCE`: such a step is logged and counted, never
hidden.
"""

import array
import dataclasses

import numpy as np

# A step reaching its tick later than this is late, s.
LATE_TOLERANCE = 0.005


@dataclasses.dataclass(frozen=True)
class TimingSummary:
  """Control-loop timing over some steps.

  Attributes:
    steps: control steps measured.
    late_steps: steps that reached their tick more than LATE_TOLERANCE late.
    period_p50: median control period, s.
    jitter_p50: median |period - nominal period|, s.
    jitter_p99: 99th percentile of |period - nominal period|, s.
    worst_late: the latest step's lateness, s (0 if none was late).
  """

  steps: int
  late_steps: int
  period_p50: float
  jitter_p50: float
  jitter_p99: float
  worst_late: float

  def line(self) -> str:
    """One line for a progress log, in milliseconds."""
    return (
      f'period p50 {self.period_p50 * 1e3:.1f} ms, jitter p50 '
      f'{self.jitter_p50 * 1e3:.1f} / p99 {self.jitter_p99 * 1e3:.1f} ms, '
      f'{self.late_steps} late'
    )


class ControlTiming:
  """Per-step periods and lateness of one control loop."""

  def __init__(self, period: float):
    self.period = period
    self._periods = array.array('d')
    self._lateness = array.array('d')
    self._last_exchange: float | None = None
    self.late_steps = 0  # Since the loop started.

  def __len__(self) -> int:
    return len(self._lateness)

  def restart(self) -> None:
    """Forgets the last exchange (a reset pauses the loop): the next step's
    period is not measured against a step before the pause."""
    self._last_exchange = None

  def record(self, lateness: float, exchange_time: float) -> bool:
    """Records a step that reached its tick `lateness` s after it (negative
    if early) and exchanged with the motors at `exchange_time`.

    Returns:
      Whether the step was late.
    """
    previous = self._last_exchange
    self._periods.append(
      float('nan') if previous is None else exchange_time - previous
    )
    self._last_exchange = exchange_time
    self._lateness.append(max(lateness, 0.0))
    late = lateness > LATE_TOLERANCE
    self.late_steps += late
    return late

  def summary(self, since: int = 0) -> TimingSummary:
    """Timing of the steps from step index `since` on (see `len`)."""
    lateness = np.frombuffer(self._lateness, float)[since:]
    periods = np.frombuffer(self._periods, float)[since:]
    periods = periods[~np.isnan(periods)]  # The first step after a reset.
    late = lateness > LATE_TOLERANCE
    if len(periods):
      jitter = np.abs(periods - self.period)
      p50, p99 = np.percentile(jitter, [50, 99])
      period = float(np.median(periods))
    else:
      p50 = p99 = period = float('nan')
    return TimingSummary(
      steps=len(lateness),
      late_steps=int(late.sum()),
      period_p50=period,
      jitter_p50=float(p50),
      jitter_p99=float(p99),
      worst_late=float(lateness.max()) if late.any() else 0.0,
    )
