"""Clocks that pace the hardware control loop.

`WallClock` keeps real time (sleeping to each control tick). `SimulatedClock`
is for a robot simulated in-process (the virtual bus): waiting advances that
simulation instead of sleeping, so runs are fast and deterministic.
"""

import time
from typing import Protocol


class Clock(Protocol):
  def now(self) -> float:
    """Seconds since an arbitrary origin."""

  def sleep_until(self, deadline: float) -> None:
    """Returns at `deadline` (at once if it has passed)."""


class WallClock:
  """Real time: `time.monotonic` and `time.sleep`."""

  def now(self) -> float:
    return time.monotonic()

  def sleep_until(self, deadline: float) -> None:
    remaining = deadline - time.monotonic()
    if remaining > 0:
      time.sleep(remaining)


class Advanceable(Protocol):
  def advance(self, seconds: float) -> None:
    """Moves a simulation forward by `seconds`."""


class SimulatedClock:
  """Time of an in-process simulated robot; waiting steps the simulation."""

  def __init__(self, simulation: Advanceable, before_advance=None):
    """Initializes the clock.

    Args:
      simulation: what waiting advances.
      before_advance: called before each advance, e.g. to make sure the
        simulated robot has received every command sent so far.
    """
    self._simulation = simulation
    self._before_advance = before_advance
    self._now = 0.0

  def now(self) -> float:
    return self._now

  def sleep_until(self, deadline: float) -> None:
    if deadline > self._now:
      if self._before_advance is not None:
        self._before_advance()
      self._simulation.advance(deadline - self._now)
      self._now = deadline
