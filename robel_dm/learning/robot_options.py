"""How a run on a robot uses its robot (`train --device_path=...`)."""

import dataclasses
import json
import pathlib
from typing import Any

from robel_dm import suite

# What --resume may change besides RunConfig's resumable fields.
RESUMABLE_OPTIONS = ('device_path', 'hours', 'wait_for_learner')


@dataclasses.dataclass(frozen=True)
class RobotRunOptions:
  """How a run uses its robot.

  Attributes:
    robot: the robot (`suite.RobotOptions`: its bus, configuration, reset,
      guide motor, tracker spec).
    dynamics: with device 'virtual', a calibration of the simulated robot.
    hours: wall-clock budget of this session, h (None: `steps` only).
    max_violations: an episode ends early once its safety violations
      (position + velocity + current) reach this; None: never.
    reset_attempts: failed resets in a row after which the run stops.
    updates_per_step: gradient updates per recorded transition, at most;
      None: the agent's own (`agents.updates_per_step`: `sac` 1, `droq`
      10).
    wait_for_learner: after every step, the robot waits until the learner
      has made the updates that step allows (`updates_per_step`), as a
      learner keeping a real robot's pace would have. None: when the robot
      runs in simulated time (device 'virtual'), where nothing else would
      hold the robot back; a real robot keeps its control period.
  """

  robot: suite.RobotOptions
  dynamics: str | None = None
  hours: float | None = None
  max_violations: int | None = None
  reset_attempts: int = 3
  updates_per_step: float | None = None
  wait_for_learner: bool | None = None

  @property
  def paced_by_learner(self) -> bool:
    """Whether the robot waits for the learner after every step."""
    if self.wait_for_learner is None:
      return self.robot.device_path == 'virtual'
    return self.wait_for_learner

  def check(self) -> None:
    """Raises ValueError naming the first bad option."""
    if self.hours is not None and not self.hours > 0:
      raise ValueError(f'hours must be > 0, got {self.hours}')
    if self.dynamics is not None and not self.robot.virtual:
      raise ValueError(
        f'--dynamics calibrates a simulated robot: the robot on '
        f'{self.robot.device_path} has its own (--device_path=virtual)'
      )
    if self.max_violations is not None and self.max_violations < 1:
      raise ValueError(
        f'max_violations must be >= 1, got {self.max_violations}'
      )
    if self.reset_attempts < 1:
      raise ValueError(
        f'reset_attempts must be >= 1, got {self.reset_attempts}'
      )
    if self.updates_per_step is not None and not (
      0 < self.updates_per_step <= 64
    ):
      raise ValueError(
        f'updates_per_step must be in (0, 64], got {self.updates_per_step}'
      )

  def to_json(self) -> dict[str, Any]:
    """The options as one flat JSON object (saved beside the run)."""
    fields = dataclasses.asdict(self)
    del fields['robot']
    return {**self.robot.to_json(), **fields}

  def load(self, config, seed: int):
    """The environment of `config`'s task (a RunConfig) on the robot."""
    return suite.load(
      config.domain,
      config.task,
      task_kwargs=config.task_kwargs,
      seed=seed,
      robot=self.robot,
      dynamics=self.dynamics,
    )

  def check_resume(self, saved_options: pathlib.Path) -> None:
    """Raises ValueError unless the options saved by the run being resumed
    (its robot.json) differ from these only in RESUMABLE_OPTIONS."""
    if not saved_options.is_file():
      raise ValueError(
        f'--resume: {saved_options} is missing (not a run on a robot)'
      )
    saved = json.loads(saved_options.read_text())
    differences = [
      f'{name}: {saved.get(name)!r} (now {value!r})'
      for name, value in self.to_json().items()
      if name not in RESUMABLE_OPTIONS and saved.get(name) != value
    ]
    if differences:
      raise ValueError(
        f'--resume: {saved_options.parent} learned with other robot options '
        '(only --device_path, --hours and --wait_for_learner may change): '
        + '; '.join(differences)
      )
