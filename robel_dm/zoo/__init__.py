"""Held-out robots: virtual D'Claws and D'Kitties that differ from the model.

Each zoo robot is a calibration file (`robel_dm.calibration`) in `robots/`
for the virtual bus: servo gains, damping, dry friction, reflected inertia
and torque limits partly outside the RandomDynamics ranges, uneven servos
(RandomDynamics draws one gain for all), a goal-to-servo delay and noisy
position sensors, on top of what every virtual servo does (positions
rounded to its 4,096 ticks a turn). Each file's `fit.about` says what
differs and why a real robot could be like it. `robel_dm.zoo.transfer`
evaluates the shipped policies on them.
"""

import dataclasses
import json
import pathlib

ROBOTS_DIRECTORY = pathlib.Path(__file__).parent / 'robots'


@dataclasses.dataclass(frozen=True)
class ZooRobot:
  """One held-out robot.

  Attributes:
    name: its file's name without '.json', e.g. 'claw_worn'.
    domain: 'dclaw' or 'dkitty'.
    path: its calibration file.
    about: what differs from the model, and why it is plausible.
  """

  name: str
  domain: str
  path: pathlib.Path
  about: str


def robots(domain: str | None = None) -> tuple[ZooRobot, ...]:
  """The zoo's robots (of one domain, if given), by name."""
  found = []
  for path in sorted(ROBOTS_DIRECTORY.glob('*.json')):
    data = json.loads(path.read_text())
    if domain is None or data['domain'] == domain:
      found.append(
        ZooRobot(path.stem, data['domain'], path, data['fit']['about'])
      )
  return tuple(found)


def robot(name: str) -> ZooRobot:
  """The zoo robot called `name`.

  Raises:
    ValueError: naming the zoo's robots, for an unknown name.
  """
  for candidate in robots():
    if candidate.name == name:
      return candidate
  names = [r.name for r in robots()]
  raise ValueError(f'no zoo robot {name!r}; the zoo has {names}')
