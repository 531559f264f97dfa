"""The D'Kitty's arena: a floor, optionally with a random heightfield."""

from dm_control import composer, mjcf
import mujoco
import numpy as np

from robel_dm import assets, environment, randomization

# ROBEL's terrain: every heightfield cell is drawn from this range, m.
TERRAIN_HEIGHT = randomization.Range(0.0, 0.05)
# The terrain a privileged observer sees: the cells of a square of
# TERRAIN_PATCH x TERRAIN_PATCH around a point (the D'Kitty's torso), about
# 0.5 m across with ROBEL's 7.6 cm cells: the ground under all four feet.
TERRAIN_PATCH = 7


class KittyFloor(composer.Arena):
  """A plane floor; with `terrain`, a heightfield regenerated per episode."""

  def _build(self, terrain: bool = False, name: str = 'floor') -> None:
    """Builds the arena.

    Args:
      terrain: add ROBEL's random heightfield (RandomDynamics variants).
      name: model name.
    """
    if not isinstance(terrain, bool):
      raise ValueError(f'terrain must be true or false, got {terrain!r}')
    path = assets.xml_path('arenas', 'kitty_floor.xml')
    self._mjcf_root = mjcf.from_path(str(path))
    self._mjcf_root.model = name
    self._terrain = terrain
    self._hfield = self._mjcf_root.find('hfield', 'terrain')
    if not terrain:
      # The flat variants have no heightfield at all (ROBEL's stayed zero,
      # hidden below the plane).
      self._mjcf_root.find('geom', 'terrain').remove()
      self._hfield.remove()
      self._hfield = None

  # The share of ROBEL's bump height the terrain gets (1: all of it; a
  # curriculum raises it from 0).
  _height_scale = 1.0

  def set_height_scale(self, scale: float) -> None:
    """Scales the heights drawn from the next `regenerate` on: 1 is
    ROBEL's terrain, 0 a flat heightfield."""
    self._height_scale = scale

  @property
  def has_terrain(self) -> bool:
    return self._terrain

  def add_marker(self, name: str, size, rgba) -> mjcf.Element:
    """Adds a non-colliding marker on a mocap body and returns the body.

    Tasks move markers by writing `data.mocap_pos`, never the model.
    """
    body = self._mjcf_root.worldbody.add('body', name=name, mocap=True)
    body.add('site', name=name, type='cylinder', size=size, rgba=rgba, group=0)
    return body

  def after_compile(self, physics, random_state) -> None:
    del random_state
    if self._hfield is None:
      return
    hfield = physics.bind(self._hfield)
    self._hfield_id = int(hfield.element_id)
    start = int(hfield.adr)
    size = int(hfield.nrow) * int(hfield.ncol)
    self._heights = physics.model.hfield_data[start : start + size]  # A view.
    self._grid = self._heights.reshape(int(hfield.nrow), int(hfield.ncol))
    # Heightfield rows run along y, columns along x, over +-size.
    self._cells_per_m = (np.array([hfield.ncol, hfield.nrow]) - 1) / (
      2 * hfield.size[:2]
    )
    self._half_size = np.array(hfield.size[:2])
    half = TERRAIN_PATCH // 2
    self._patch_offsets = np.arange(-half, half + 1)

  def regenerate(
    self, physics: mjcf.Physics, random_state: np.random.RandomState
  ) -> None:
    """Draws new terrain heights (no-op without terrain)."""
    if self._hfield is None:
      return
    self._heights[:] = TERRAIN_HEIGHT.sample(random_state, self._heights.size)
    if self._height_scale != 1.0:
      self._heights *= self._height_scale
    # A renderer keeps its own copy of the heightfield: refresh it if one
    # exists (without making one).
    contexts = environment.existing_render_contexts(physics)
    if contexts:
      with contexts.gl.make_current() as ctx:
        ctx.call(
          mujoco.mjr_uploadHField,
          physics.model.ptr,
          contexts.mujoco.ptr,
          self._hfield_id,
        )

  def terrain_around(self, xy) -> np.ndarray:
    """The heights of the `TERRAIN_PATCH`^2 cells around the floor point
    `xy` (m, world), scaled to [-1, 1] over ROBEL's range; rows along y.

    Raises:
      ValueError: on an arena without terrain.
    """
    if self._hfield is None:
      raise ValueError('this floor has no terrain')
    column, row = np.rint(
      (np.asarray(xy[:2]) + self._half_size) * self._cells_per_m
    ).astype(int)
    # Past the field's edge (4.5 m out) the edge cells stand in.
    rows = np.clip(row + self._patch_offsets, 0, self._grid.shape[0] - 1)
    columns = np.clip(column + self._patch_offsets, 0, self._grid.shape[1] - 1)
    heights = self._grid[np.ix_(rows, columns)].ravel()
    low, high = TERRAIN_HEIGHT.low, TERRAIN_HEIGHT.high
    return 2.0 * (heights - low) / (high - low) - 1.0

  @property
  def terrain_heights(self) -> np.ndarray | None:
    """The current heightfield heights, m (a view), or None."""
    return None if self._hfield is None else self._heights
