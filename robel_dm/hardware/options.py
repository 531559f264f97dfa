"""How to reach a robot: one value, built once, passed whole down.

A command builds a `RobotOptions` from its flags (or a user in Python), and
`suite.load(..., robot=options)` hands it down unchanged to the hardware
environment, which opens what it names. It imports nothing heavy, so the
suite and the commands can build it without the hardware layer's
dependencies.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from robel_dm import constants

if TYPE_CHECKING:
  from collections.abc import Callable

  from robel_dm.hardware.config import RobotConfig
  from robel_dm.hardware.tracking.tracker import TorsoTracker

# Guide motor modes: it shows the task's goal, or a person turns it to set
# the goal.
GUIDE_SHOWS_GOAL = 'show'
GUIDE_SETS_GOAL = 'interactive'
GUIDE_MODES = (GUIDE_SHOWS_GOAL, GUIDE_SETS_GOAL)
RESET_NAMES = ('scripted', 'move', 'manual')


@dataclasses.dataclass(frozen=True)
class RobotOptions:
  """A robot to run a task on, and how.

  Attributes:
    device_path: the Dynamixel bus's serial device ('/dev/ttyUSB0', a
      standalone virtual bus's pseudo-terminal), or 'virtual' for an
      in-process virtual bus driven by a simulation in simulated time.
    robot_config: a `RobotConfig`, or the path of a JSON robot
      configuration; ROBEL's configuration of the robot if None.
    reset: 'scripted', 'move' or 'manual' (see `hardware.resets`), or a
      procedure; the robot's default if None.
    guide: D'Claw Turn/Screw: ROBEL's guide motor 'show's the goal, or
      ('interactive') a person turns it to set the goal; None: no guide.
    tracker: the D'Kitty's motion tracker: a `TorsoTracker`, or its spec
      (`--tracker=natnet:...`, see `hardware.tracking.spec`), opened when
      the environment is built and closed with it.
  """

  device_path: str
  robot_config: str | RobotConfig | None = None
  reset: str | Callable[..., None] | None = None
  guide: str | None = None
  tracker: str | TorsoTracker | None = None

  def __post_init__(self):
    if not isinstance(self.device_path, str) or not self.device_path:
      raise ValueError(
        f'device_path must name a bus (or be {constants.VIRTUAL_DEVICE!r}), '
        f'got {self.device_path!r}'
      )
    if self.guide is not None and self.guide not in GUIDE_MODES:
      raise ValueError(
        f'guide must be one of {GUIDE_MODES}, got {self.guide!r}'
      )
    if isinstance(self.reset, str) and self.reset not in RESET_NAMES:
      raise ValueError(
        f"unknown reset {self.reset!r}; expected 'scripted', 'move' or "
        "'manual' (or a procedure)"
      )
    if isinstance(self.tracker, str):
      # Imported here: a tracker spec is rare, its parser needs sockets.
      from robel_dm.hardware.tracking import spec  # noqa: PLC0415

      spec.parse(self.tracker)  # A bad spec fails before anything is built.

  @property
  def virtual(self) -> bool:
    """Whether this is the in-process virtual bus."""
    return self.device_path == constants.VIRTUAL_DEVICE

  def to_json(self) -> dict:
    """The options as JSON (the configuration and tracker by path/spec)."""
    for name in ('robot_config', 'reset', 'tracker'):
      value = getattr(self, name)
      if value is not None and not isinstance(value, str):
        raise ValueError(f'{name} is an object, not a path or name: {value!r}')
    return dataclasses.asdict(self)
