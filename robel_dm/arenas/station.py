"""The D'Claw station: a mount for the claw above a floor."""

from dm_control import composer, mjcf

from robel_dm import assets

# Height of the claw mount above the floor, m (docs/robel_reference.md
# section 3.2): the valve scenes mount the claw 35 mm higher than the pose
# scene.
MOUNT_HEIGHT_POSE = 0.30
MOUNT_HEIGHT_VALVE = 0.335


class ClawStation(composer.Arena):
  """Floor, lights, cameras, the claw mount and a goal-angle marker."""

  def _build(
    self,
    mount_height: float = MOUNT_HEIGHT_VALVE,
    show_goal: bool = True,
    name: str = 'station',
  ) -> None:
    """Builds the station.

    Args:
      mount_height: height of the claw's mount point above the floor, m.
      show_goal: whether the goal-angle marker is visible.
      name: model name.
    """
    path = assets.xml_path('arenas', 'claw_station.xml')
    self._mjcf_root = mjcf.from_path(str(path))
    self._mjcf_root.model = name
    self._mount = self._mjcf_root.find('body', 'mount')
    self._mount.pos = (0.0, 0.0, mount_height)
    self._claw_site = self._mjcf_root.find('site', 'claw_attachment')
    self._goal = self._mjcf_root.find('body', 'goal')
    if not show_goal:
      self._mjcf_root.find('site', 'goal_mark').rgba = (0, 0, 0, 0)

  @property
  def mount(self) -> mjcf.Element:
    """The body the claw hangs from."""
    return self._mount

  @property
  def mount_geom(self) -> mjcf.Element:
    return self._mount.find('geom', 'mount')

  @property
  def goal_body(self) -> mjcf.Element:
    """Mocap body whose yaw shows the goal angle."""
    return self._goal

  def attach_claw(self, claw: composer.Entity) -> mjcf.Element:
    """Hangs `claw` from the mount and returns the attachment frame."""
    return self.attach(claw, attach_site=self._claw_site)
