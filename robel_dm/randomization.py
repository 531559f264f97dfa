"""Per-episode dynamics randomization on the compiled model.

Every dynamics range ROBEL randomizes lives here, as data
(docs/robel_reference.md sections 2.1-2.4, 6); the terrain's is the arena's
(`arenas/floor.py`). The randomizer writes the compiled `MjModel` in place
with one vectorized write per quantity, always relative to a nominal snapshot
taken after compilation, so draws never compound across episodes and the
MJCF is never recompiled.
"""

import dataclasses

from dm_control import mjcf
import mujoco
import numpy as np

# ROBEL draws geom friction as absolute values meant for its default
# (metal) friction; robel_dm applies the draw as a factor relative to this
# reference so that low-friction plastic parts keep their ratio to the rest.
REFERENCE_FRICTION = np.array([1.0, 0.005, 0.0001])


@dataclasses.dataclass(frozen=True)
class Range:
  """A uniform range U(low, high); `low` and `high` may be arrays."""

  low: float | tuple[float, ...]
  high: float | tuple[float, ...]

  def __post_init__(self):
    low, high = np.asarray(self.low, float), np.asarray(self.high, float)
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
      raise ValueError(f'a range needs finite ends: {self.low}, {self.high}')
    if np.any(low > high):
      raise ValueError(f'empty range: low {self.low} > high {self.high}')

  def sample(
    self, random_state: np.random.RandomState, size=None
  ) -> np.ndarray:
    return random_state.uniform(self.low, self.high, size)

  def contains(self, values) -> bool:
    values = np.asarray(values)
    return bool(np.all((values >= self.low) & (values <= self.high)))


@dataclasses.dataclass(frozen=True)
class DynamicsRanges:
  """What a RandomDynamics variant randomizes. `None` leaves it nominal.

  Attributes:
    damping: joint damping, N m s/rad.
    damping_shared: one draw for all joints (else one per joint).
    friction_loss: joint friction loss, N m.
    friction_loss_shared: one draw for all joints (else one per joint).
    actuator_kp: position gain of every actuator, one draw, N m/rad.
    geom_friction: (slide, spin, roll) friction, one draw for all geoms,
      applied relative to `REFERENCE_FRICTION`.
    mount_offset: offset of the robot mount from nominal, per axis, m.
    color: RGB of decorated geoms, per geom and channel.
    total_mass: total mass of the model, kg.
  """

  damping: Range | None = None
  damping_shared: bool = False
  friction_loss: Range | None = None
  friction_loss_shared: bool = False
  actuator_kp: Range | None = None
  geom_friction: Range | None = None
  mount_offset: Range | None = None
  color: Range | None = None
  total_mass: Range | None = None

  def __post_init__(self):
    # Physical quantities that a negative draw would make diverge.
    for name in _NONNEGATIVE:
      value = getattr(self, name)
      if value is None:
        continue
      if not isinstance(value, Range):
        raise ValueError(f'dynamics.{name} must be a Range, got {value!r}')
      if np.any(np.asarray(value.low) < 0):
        raise ValueError(f'dynamics.{name} must not go below 0: {value}')


# The ranges of `DynamicsRanges` that cannot be negative.
_NONNEGATIVE = (
  'damping', 'friction_loss', 'actuator_kp', 'geom_friction', 'total_mass'
)  # fmt: skip


# --- ROBEL's ranges --------------------------------------------------------

_ROBEL_GEOM_FRICTION = Range(low=(0.8, 0.003, 5e-5), high=(1.2, 0.007, 1.5e-4))

DCLAW_POSE = DynamicsRanges(
  damping=Range(0.005, 0.1),
  friction_loss=Range(0.001, 0.005),
  actuator_kp=Range(1.0, 3.0),
)

DCLAW_VALVE = dataclasses.replace(
  DCLAW_POSE,
  geom_friction=_ROBEL_GEOM_FRICTION,
  mount_offset=Range(-0.01, 0.01),
  color=Range(0.2, 0.9),
)


DKITTY_STAND = DynamicsRanges(
  damping=Range(0.1, 0.2),
  damping_shared=True,
  friction_loss=Range(0.001, 0.005),
  friction_loss_shared=True,
  actuator_kp=Range(2.0, 4.0),
  geom_friction=_ROBEL_GEOM_FRICTION,
  total_mass=Range(1.6, 2.0),
)

# Orient and Walk draw the servo gain from a narrower range.
DKITTY_LOCOMOTION = dataclasses.replace(
  DKITTY_STAND, actuator_kp=Range(2.8, 3.2)
)


@dataclasses.dataclass(frozen=True)
class Targets:
  """The model elements a randomizer acts on.

  Attributes:
    joints: joints whose damping and friction loss vary.
    actuators: position actuators whose gain varies.
    mount: body whose position is perturbed.
    colored_geoms: geoms whose colour varies.
  """

  joints: tuple[mjcf.Element, ...] = ()
  actuators: tuple[mjcf.Element, ...] = ()
  mount: mjcf.Element | None = None
  colored_geoms: tuple[mjcf.Element, ...] = ()


class DynamicsRandomizer:
  """Applies `DynamicsRanges` to a compiled model at every episode start."""

  def __init__(self, ranges: DynamicsRanges, targets: Targets):
    self._ranges = ranges
    self._targets = targets
    self._nominal = None
    # What `draws` holds: fixed by the ranges and targets.
    self._quantities = self._drawn_quantities()
    self._draws = np.zeros(self.draw_count)
    self._scale = 1.0

  @property
  def scale(self) -> float:
    """How far each episode's physics is from the nominal robot's: 1 (the
    default) applies the draws, 0 the nominal values, between them the
    same fraction of each draw's distance from nominal (a curriculum over
    the ranges). The draws themselves do not depend on it."""
    return self._scale

  @scale.setter
  def scale(self, value: float) -> None:
    if not 0.0 <= value <= 1.0:
      raise ValueError(f'randomization scale must be in [0, 1], got {value}')
    self._scale = float(value)

  def _toward_nominal(self, drawn, nominal):
    """`drawn` moved to `scale` of its distance from `nominal` (exactly
    `drawn` at scale 1)."""
    if self._scale == 1.0:
      return drawn
    return nominal + self._scale * (np.asarray(drawn) - nominal)

  @property
  def draws(self) -> np.ndarray:
    """The episode's draws (as drawn: before `scale` moves them toward
    nominal), each scaled to [-1, 1] over its range (a view,
    rewritten by `apply`): damping, friction loss, servo gain, contact
    friction, mount offset and total mass, those randomized, in that order
    (colour is left out: it changes nothing the physics sees). What a
    privileged observer knows and a policy on a robot does not."""
    return self._draws

  @property
  def ranges(self) -> DynamicsRanges:
    return self._ranges

  def after_compile(self, physics: mjcf.Physics) -> None:
    """Caches model addresses and snapshots the nominal values."""
    model = physics.model
    targets = self._targets
    self._dofs = (
      physics.bind(targets.joints).dofadr if targets.joints else np.zeros(0)
    ).astype(int)
    self._actuators = (
      physics.bind(targets.actuators).element_id
      if targets.actuators
      else np.zeros(0, int)
    )
    self._mount = (
      physics.bind(targets.mount).element_id if targets.mount else None
    )
    self._colored = (
      physics.bind(targets.colored_geoms).element_id
      if targets.colored_geoms
      else np.zeros(0, int)
    )
    self._nominal = {
      'dof_damping': model.dof_damping.copy(),
      'dof_frictionloss': model.dof_frictionloss.copy(),
      'gainprm': model.actuator_gainprm.copy(),
      'biasprm': model.actuator_biasprm.copy(),
      'geom_friction': model.geom_friction.copy(),
      'body_pos': model.body_pos.copy(),
      'geom_rgba': model.geom_rgba.copy(),
      'body_mass': model.body_mass.copy(),
      'body_inertia': model.body_inertia.copy(),
    }

  def draws_by_quantity(self) -> dict[str, np.ndarray]:
    """`draws` split by `DynamicsRanges` field, in its order (copies)."""
    split, offset = {}, 0
    for name, size in self._quantities:
      split[name] = self._draws[offset : offset + size].copy()
      offset += size
    return split

  @property
  def draw_count(self) -> int:
    """The size of `draws`."""
    return sum(size for _, size in self._quantities)

  def _drawn_quantities(self) -> list[tuple[str, int]]:
    """(`DynamicsRanges` field, number of draws) of what `draws` holds."""
    ranges = self._ranges
    n_dofs = len(self._targets.joints)
    sizes = {
      'damping': 1 if ranges.damping_shared else n_dofs,
      'friction_loss': 1 if ranges.friction_loss_shared else n_dofs,
      'actuator_kp': 1,
      'geom_friction': 3,
      'mount_offset': 3 if self._targets.mount is not None else 0,
      'total_mass': 1,
    }
    return [
      (name, size)
      for name, size in sizes.items()
      if getattr(ranges, name) is not None and size
    ]

  def _record_draws(self, drawn: dict[str, np.ndarray]) -> None:
    """Writes `draws`: each drawn value scaled to [-1, 1] over its range."""
    offset = 0
    for name, size in self._quantities:
      span = getattr(self._ranges, name)
      low, high = np.asarray(span.low, float), np.asarray(span.high, float)
      width = np.where(high > low, high - low, 1.0)
      self._draws[offset : offset + size] = (
        2.0 * (drawn[name] - low) / width - 1.0
      )
      offset += size

  def apply(
    self, physics: mjcf.Physics, random_state: np.random.RandomState
  ) -> None:
    """Draws new dynamics and writes them into the compiled model."""
    if self._nominal is None:
      raise RuntimeError('DynamicsRandomizer.after_compile was not called')
    model = physics.model
    ranges = self._ranges
    n_dofs = len(self._dofs)
    drawn = {}
    nominal = self._nominal
    if ranges.damping is not None:
      size = None if ranges.damping_shared else n_dofs
      drawn['damping'] = ranges.damping.sample(random_state, size)
      model.dof_damping[self._dofs] = self._toward_nominal(
        drawn['damping'], nominal['dof_damping'][self._dofs]
      )
    if ranges.friction_loss is not None:
      size = None if ranges.friction_loss_shared else n_dofs
      drawn['friction_loss'] = ranges.friction_loss.sample(random_state, size)
      model.dof_frictionloss[self._dofs] = self._toward_nominal(
        drawn['friction_loss'], nominal['dof_frictionloss'][self._dofs]
      )
    if ranges.actuator_kp is not None:
      # A position servo's force is kp * (ctrl - q): gain and bias together.
      drawn['actuator_kp'] = ranges.actuator_kp.sample(random_state)
      kp = self._toward_nominal(
        drawn['actuator_kp'], nominal['gainprm'][self._actuators, 0]
      )
      model.actuator_gainprm[self._actuators, 0] = kp
      model.actuator_biasprm[self._actuators, 1] = -kp
    if ranges.geom_friction is not None:
      drawn['geom_friction'] = ranges.geom_friction.sample(random_state)
      factor = self._toward_nominal(
        drawn['geom_friction'] / REFERENCE_FRICTION, 1.0
      )
      np.multiply(nominal['geom_friction'], factor, out=model.geom_friction)
    if ranges.mount_offset is not None and self._mount is not None:
      drawn['mount_offset'] = ranges.mount_offset.sample(random_state, 3)
      model.body_pos[self._mount] = nominal['body_pos'][
        self._mount
      ] + self._toward_nominal(drawn['mount_offset'], 0.0)
    if ranges.color is not None and len(self._colored):
      model.geom_rgba[self._colored, :3] = ranges.color.sample(
        random_state, (len(self._colored), 3)
      )
    if ranges.total_mass is not None:
      # mj_setTotalmass scales the current masses: start from nominal.
      model.body_mass[:] = self._nominal['body_mass']
      model.body_inertia[:] = self._nominal['body_inertia']
      drawn['total_mass'] = ranges.total_mass.sample(random_state)
      mujoco.mj_setTotalmass(
        model.ptr,
        self._toward_nominal(
          drawn['total_mass'], float(np.sum(nominal['body_mass']))
        ),
      )
      # Derived constants (dof_invweight0, body_subtreemass, ...) are stale
      # until recomputed.
      mujoco.mj_setConst(model.ptr, physics.data.ptr)
    self._record_draws(drawn)


def noise_halfwidths(widths, fraction: float) -> np.ndarray:
  """ROBEL's observation noise is fraction * U(-0.5, 0.5) * range width.

  Args:
    widths: widths of the joints' ranges.
    fraction: ROBEL's `sim_observation_noise`.

  Returns:
    The half-widths of the uniform noise, fraction * width / 2.
  """
  return fraction * np.asarray(widths, dtype=float) / 2
