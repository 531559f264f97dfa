"""Pieces shared by the servo-driven robots (D'Claw, D'Kitty)."""

import pathlib

from dm_control import composer, mjcf
from dm_control.composer.observation import observable


def load_model(path: pathlib.Path, name: str) -> mjcf.RootElement:
  """Loads an MJCF model and names it (the name prefixes its elements)."""
  root = mjcf.from_path(str(path))
  root.model = name
  return root


def find_all(root: mjcf.RootElement, kind: str, names) -> tuple:
  """The named elements of one kind, in order.

  Raises:
    ValueError: naming the elements the model lacks.
  """
  elements = tuple(root.find(kind, name) for name in names)
  missing = [n for n, e in zip(names, elements, strict=True) if e is None]
  if missing:
    raise ValueError(f'model {root.model!r} has no {kind} {missing}')
  return elements


class JointObservables(composer.Observables):
  """Joint angles and velocities of a robot with a `joints` property."""

  @composer.observable
  def joints_pos(self):
    return observable.MJCFFeature('qpos', self._entity.joints)

  @composer.observable
  def joints_vel(self):
    return observable.MJCFFeature('qvel', self._entity.joints)
