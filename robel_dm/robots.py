"""The robots, declared once: what every layer needs to know of each.

Each `Robot` names what the layers read instead of keeping their own tables
keyed by 'dclaw' or 'dkitty': the task registry (one per robot), the
Gymnasium ids' prefix, the video camera, the scene a standalone virtual bus
simulates, the shipped hardware configuration and the default reset. The
rest of a robot is code in the layer it belongs to, found by the robot's
name: its model and entity (`xml/`, `entities/`), its tasks (`tasks/`,
registered in `registry.DOMAINS[name]`), its hardware configuration
(`hardware/configs/<name>.json`) and its scripted reset, if any
(`hardware/resets.py`). docs/architecture.md ("One place per robot")
lists them.
"""

import dataclasses


@dataclasses.dataclass(frozen=True)
class Robot:
  """One robot.

  Attributes:
    name: the domain name (`suite.load(name, ...)`, flags, file names).
    title: its name in prose.
    gym_prefix: the first word of its Gymnasium ids (ROBEL's env names).
    default_camera: the camera videos use unless told otherwise.
    standalone_scene: the task whose scene a standalone virtual bus
      simulates (one with every motor's joint).
    scripted_reset_with_object: whether, on a robot, tasks with an object
      (the D'Claw's valve) reset with the scripted procedure by default
      (else with one move to the initial pose).
    unattended_reset: the reset for many episodes in a row on a virtual
      bus, whatever ended the last one: 'manual' for a robot that can
      fall (the bus's simulated person stands it up), None for the task's
      default.
  """

  name: str
  title: str
  gym_prefix: str
  default_camera: str
  standalone_scene: str
  scripted_reset_with_object: bool = False
  unattended_reset: str | None = None

  @property
  def config_file(self) -> str:
    """The shipped hardware configuration, in `hardware/configs/`."""
    return f'{self.name}.json'


DCLAW = Robot(
  name='dclaw',
  title="D'Claw",
  gym_prefix='DClaw',
  default_camera='front',
  standalone_scene='turn_fixed',
  scripted_reset_with_object=True,
)
DKITTY = Robot(
  name='dkitty',
  title="D'Kitty",
  gym_prefix='DKitty',
  default_camera='follow',
  standalone_scene='stand_fixed',
  unattended_reset='manual',
)
ROBOTS: dict[str, Robot] = {robot.name: robot for robot in (DCLAW, DKITTY)}
