"""The D'Claw valve stations: a free-turning 3- or 4-prong valve."""

from dm_control import composer, mjcf
from dm_control.composer.observation import observable

from robel_dm import assets

# Valve variant name -> model file. ROBEL shipped an environment only for the
# 3-prong valve; the 4-prong one existed as a model alone.
VARIANTS = {'valve3': 'valve3.xml', 'valve4': 'valve4.xml'}


class Valve(composer.Entity):
  """A valve on a static base; its hinge turns without limit."""

  def _build(self, variant: str = 'valve3', name: str = 'valve') -> None:
    """Loads the model.

    Args:
      variant: 'valve3' (three prongs) or 'valve4' (four prongs).
      name: model name; the same for both variants so observation keys agree.

    Raises:
      ValueError: for an unknown variant.
    """
    if variant not in VARIANTS:
      raise ValueError(
        f'unknown valve {variant!r}: expected one of {sorted(VARIANTS)}'
      )
    self._variant = variant
    path = assets.xml_path('valve', VARIANTS[variant])
    self._mjcf_root = mjcf.from_path(str(path))
    self._mjcf_root.model = name
    self._hinge = self._mjcf_root.find('joint', 'hinge')
    self._valve_body = self._mjcf_root.find('body', 'valve')

  def _build_observables(self) -> 'ValveObservables':
    return ValveObservables(self)

  @property
  def mjcf_model(self) -> mjcf.RootElement:
    return self._mjcf_root

  @property
  def variant(self) -> str:
    return self._variant

  @property
  def hinge(self) -> mjcf.Element:
    return self._hinge

  @property
  def valve_body(self) -> mjcf.Element:
    """The turning body (hub and prongs)."""
    return self._valve_body

  @property
  def valve_geoms(self) -> tuple[mjcf.Element, ...]:
    return tuple(
      self._valve_body.find_all('geom', immediate_children_only=True)
    )


class ValveObservables(composer.Observables):
  """Valve angle (unwrapped, rad) and angular velocity (rad/s)."""

  @composer.observable
  def angle(self):
    return observable.MJCFFeature('qpos', self._entity.hinge)

  @composer.observable
  def angular_velocity(self):
    return observable.MJCFFeature('qvel', self._entity.hinge)
