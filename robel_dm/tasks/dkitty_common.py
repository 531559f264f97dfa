"""Pieces shared by the D'Kitty tasks: scene, torso state and uprightness.

The D'Kitty's root is a free joint. ROBEL's root was six joints (three slides,
then hinges about x, y and z) on a frame 0.3 m above the floor, and its torso
observations are kept with their meanings and units:
  * `root_pos`: torso position relative to that frame origin (0, 0, 0.3), m;
  * `root_euler`: rotating-frame x-y-z Euler angles of the torso, rad
    (R = Rx(a) Ry(b) Rz(c), transforms3d's 'rxyz');
  * `root_vel`: world linear velocity, m/s;
  * `root_angular_vel`: rates of those Euler angles, rad/s (ROBEL read its
    hinge velocities, which are exactly these rates);
  * `upright`: cosine between the torso z-axis and world z.
"""

import dataclasses
import math

from dm_control import mjcf
import numpy as np

from robel_dm import constants, geometry, randomization
from robel_dm.arenas import floor
from robel_dm.entities import dkitty
from robel_dm.tasks import base

# Observation features every D'Kitty task has, in ROBEL's observation-dict
# order; the first five come from the torso, contiguously.
TORSO_FEATURES = {
  'upright': 1,
  'root_pos': 3,
  'root_euler': 3,
  'root_vel': 3,
  'root_angular_vel': 3,
}
FEATURES = {
  **TORSO_FEATURES,
  'kitty_qpos': 12,
  'kitty_qvel': 12,
  'last_action': 12,
}
# The part of ROBEL's default flattened observation all D'Kitty tasks share.
DEFAULT_OBSERVATION_KEYS = (
  'root_pos', 'root_euler', 'kitty_qpos', 'root_vel', 'root_angular_vel',
  'kitty_qvel', 'last_action', 'upright',
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Upright:
  """ROBEL's uprightness terms and falling condition.

  ROBEL's definition: docs/robel_reference.md section 2.4.

  Attributes:
    threshold: the robot has fallen when `upright` drops below this.
    reward: weight of (upright - threshold) / (1 - threshold).
    falling_reward: added (a penalty) once fallen.
  """

  threshold: float
  reward: float
  falling_reward: float

  def terms(self, upright: float) -> tuple[float, float]:
    """Returns the (upright, falling) reward terms."""
    scale = (upright - self.threshold) / (1.0 - self.threshold)
    falling = self.falling_reward if upright < self.threshold else 0.0
    return self.reward * scale, falling

  def fallen(self, upright: float) -> bool:
    return upright < self.threshold


class KittyScene:
  """The D'Kitty on its free joint in a `KittyFloor` arena."""

  def __init__(self, terrain: bool):
    self.arena = floor.KittyFloor(terrain=terrain)
    self.robot = dkitty.DKitty()
    frame = self.arena.add_free_entity(self.robot)
    # The free joint's default pose: standing height, so that a data reset
    # does not sink the legs into the floor (a costly contact solve).
    frame.pos = dkitty.ROBEL_FRAME_ORIGIN
    self.root_joint = frame.freejoint


class Torso:
  """Reads the torso's pose and velocity from the free joint and `xmat`."""

  def __init__(self, scene: KittyScene):
    self._root_joint = scene.root_joint
    self._torso = scene.robot.torso
    self.position = np.zeros(3)  # World position, m.
    self.rotation = np.eye(3)  # Torso-to-world rotation.

  def after_compile(self, physics: mjcf.Physics) -> None:
    root = physics.bind(self._root_joint)
    qpos, dof = int(root.qposadr), int(root.dofadr)
    self._qpos = physics.data.qpos[qpos : qpos + 7]  # Views of MjData.
    self._qvel = physics.data.qvel[dof : dof + 6]
    body = int(physics.bind(self._torso).element_id)
    self._xmat = physics.data.xmat[body].reshape(3, 3)

  def place(self, position, yaw: float) -> None:
    """Puts the torso at `position` (world, m), level, turned by `yaw`."""
    self._qpos[:3] = position
    self._qpos[3:] = geometry.yaw_quaternion(yaw)
    self._qvel[:] = 0.0

  def update(self, out: np.ndarray) -> None:
    """Reads the torso and writes the torso features.

    Args:
      out: 13 values, `TORSO_FEATURES` in order (upright, root_pos,
        root_euler, root_vel, root_angular_vel).
    """
    self.position[:] = self._qpos[:3]
    self.rotation[:] = self._xmat
    rotation = self.rotation.tolist()
    euler = geometry.euler_xyz(rotation)
    # The free joint's angular velocity is in the torso frame.
    # Row by row in numpy's own order (see geometry.dot), not BLAS.
    angular_velocity = np.add.reduce(self.rotation * self._qvel[3:], axis=1)
    position = self.position - dkitty.ROBEL_FRAME_ORIGIN
    out[:] = (
      rotation[2][2],
      *position,
      *euler,
      *self._qvel[:3],
      *geometry.euler_xyz_rates(euler, angular_velocity.tolist()),
    )

  @property
  def upright(self) -> float:
    return float(self.rotation[2, 2])

  @property
  def facing(self) -> np.ndarray:
    """The torso's forward (y) axis projected on the floor (not unit)."""
    return self.rotation[:2, 1]


@dataclasses.dataclass(frozen=True)
class Marker:
  """A mocap marker of a floor target: a cylinder (radius, half-height),
  coloured, its centre this high above the target, m."""

  name: str
  size: tuple[float, float]
  rgba: tuple[float, float, float, float]
  height: float


class FloorTarget:
  """A target on the floor, shown by markers that stand on it.

  On a robot with a motion tracker that sees the target, the tracked
  position replaces the placed one every step (`track`).
  """

  def __init__(self, arena: floor.KittyFloor, *markers: Marker):
    self._bodies = [
      arena.add_marker(m.name, size=m.size, rgba=m.rgba) for m in markers
    ]
    self._heights = [m.height for m in markers]
    self.position = np.zeros(2)  # x, y, m.

  def after_compile(self, physics: mjcf.Physics) -> None:
    mocap_pos = physics.data.mocap_pos
    self._marker_pos = [  # Views of MjData.
      mocap_pos[base.mocap_index(physics, body)] for body in self._bodies
    ]

  def place(self, angle: float, distance: float) -> None:
    """Puts the target `distance` m from the origin along `angle` rad
    (counter-clockwise from +x), with its markers."""
    self.position[:] = math.cos(angle), math.sin(angle)
    self.position *= distance
    for marker, height in zip(self._marker_pos, self._heights, strict=True):
      marker[:] = (*self.position, height)

  def track(self, robot_io) -> None:
    """Takes the tracked target's position, if the robot tracks one."""
    tracked = robot_io.tracked_target()
    if tracked is not None:
      self.position[:] = tracked


class KittyParts:
  """What every D'Kitty task does the same way, for composition in a task.

  Builds the scene, places the robot at reset (regenerating the terrain),
  and reads the torso and legs into the shared features once per step.
  """

  def __init__(self, terrain: bool, upright: Upright):
    self.scene = KittyScene(terrain=terrain)
    self.torso = Torso(self.scene)
    self.upright = upright
    self._targets = []

  def add_target(self, *markers: Marker) -> FloorTarget:
    """A target on the floor with these markers, bound with the parts."""
    target = FloorTarget(self.arena, *markers)
    self._targets.append(target)
    return target

  @property
  def arena(self) -> floor.KittyFloor:
    return self.scene.arena

  @property
  def robot(self) -> dkitty.DKitty:
    return self.scene.robot

  def task_scene(self, episode_steps: int) -> base.Scene:
    """The `RobelTask` scene of a D'Kitty task.

    Args:
      episode_steps: the task's episode length, control steps.
    """
    robot = self.robot
    return base.Scene(
      arena=self.arena,
      robot=robot,
      control_timestep=constants.CONTROL_TIMESTEP,
      episode_steps=episode_steps,
      randomizer_targets=randomization.Targets(
        joints=robot.joints, actuators=robot.actuators
      ),
      root_joint=self.scene.root_joint,
      privileged_state=self.terrain_under_torso
      if self.arena.has_terrain
      else None,
      privileged_size=floor.TERRAIN_PATCH**2 if self.arena.has_terrain else 0,
      set_randomization_scale=self.arena.set_height_scale
      if self.arena.has_terrain
      else None,
    )

  def terrain_under_torso(self) -> np.ndarray:
    """The terrain around the torso (`KittyFloor.terrain_around`)."""
    return self.arena.terrain_around(self.torso.position)

  def bind_features(self, task) -> None:
    """Takes the task's torso and leg feature views, which `update` fills."""
    self._torso_features = task.feature_span('upright', 'root_angular_vel')
    self._joint_features = task.feature_span('kitty_qpos', 'kitty_qvel')

  def after_compile(self, physics: mjcf.Physics) -> None:
    self.torso.after_compile(physics)
    for target in self._targets:
      target.after_compile(physics)

  def reset(
    self, physics, random_state, leg_pose, position=None, yaw: float = 0.0
  ) -> None:
    """Draws terrain and places the robot still, legs at `leg_pose`.

    Args:
      physics: the physics, inside `reset_context`.
      random_state: the episode's random state.
      leg_pose: 12 joint angles, rad; also commanded to the servos.
      position: torso position (world, m); ROBEL's frame origin if None.
      yaw: torso heading about z, rad (0 faces +y).
    """
    self.arena.regenerate(physics, random_state)
    physics.bind(self.robot.joints).qpos = leg_pose
    physics.bind(self.robot.actuators).ctrl = leg_pose
    if position is None:
      position = dkitty.ROBEL_FRAME_ORIGIN
    self.torso.place(position, yaw)
    # Bring derived quantities up to date: the next (legacy) physics step
    # continues from them.
    physics.forward()

  def update(self, sensed_qpos, sensed_qvel) -> None:
    """Reads torso and legs into the features."""
    self.torso.update(self._torso_features)
    self._joint_features[:12] = sensed_qpos
    self._joint_features[12:] = sensed_qvel

  def upright_terms(self) -> dict[str, float]:
    """The 'upright' and 'falling' reward terms of the last update."""
    upright, falling = self.upright.terms(self.torso.upright)
    return {'upright': upright, 'falling': falling}

  def fallen(self) -> bool:
    """Whether the robot had fallen at the last update."""
    return self.upright.fallen(self.torso.upright)
