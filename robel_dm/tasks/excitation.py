"""Joint excitation: the robot alone, following joint targets, for system
identification.

Not a benchmark task (it is not in the registry): `suite.load_excitation`
builds it, and `robel-sysid excite` drives it through an
excitation sequence while recording (see docs/sysid.md). The D'Claw hangs in
its pose station with nothing to touch; the D'Kitty is held on a stand, its
feet in the air, as a robot is set up for this on the bench. Actions are
ROBEL's normalized joint targets, with the same velocity clamp as every task.
The reward is the negative distance between the targets and the joints, so
a recording shows how well the servos track.
"""

from dm_control import composer
import numpy as np

from robel_dm import geometry, numeric
from robel_dm.arenas import floor, station
from robel_dm.entities import dclaw, dkitty
from robel_dm.tasks import base

# Control timestep of excitation, s: 50 Hz, so that a servo's response (its
# time constant is about 50 ms on the D'Claw) is sampled several times. A
# D'Kitty's state read takes under 5 ms on a 1 Mbps bus.
CONTROL_TIMESTEP = 0.02
# Height of the D'Kitty's stand: the torso's origin above the floor, m. The
# legs (0.25 m fully stretched) then swing clear of the floor.
KITTY_STAND_HEIGHT = 0.45
# The pose every excitation starts from and moves around, rad: the claw's
# fingers bent (gravity loads the middle and distal joints) inside the action
# range, the kitty's legs crouched.
CENTER_POSE = {
  'dclaw': np.tile([0.0, -0.5, 0.8], 3),
  'dkitty': dkitty.CROUCHED_POSE,
}
DOMAINS = tuple(CENTER_POSE)
# Each robot's joints, in action order (what `--joints` may name).
JOINT_NAMES = {'dclaw': dclaw.JOINT_NAMES, 'dkitty': dkitty.JOINT_NAMES}


def _scene(domain: str) -> tuple[composer.Arena, composer.Robot]:
  if domain == 'dclaw':
    arena = station.ClawStation(
      mount_height=station.MOUNT_HEIGHT_POSE, show_goal=False
    )
    robot = dclaw.DClaw()
    arena.attach_claw(robot)
  else:
    arena = floor.KittyFloor(terrain=False)
    robot = dkitty.DKitty()
    frame = arena.attach(robot)  # Fixed to the world: on its stand.
    frame.pos = (0.0, 0.0, KITTY_STAND_HEIGHT)
  return arena, robot


class JointExcitation(base.RobelTask):
  """The robot alone, its joints following the commanded targets."""

  REWARD_TERMS = ('tracking_error_cost',)

  def __init__(self, domain: str, duration: float, **options):
    """Builds the scene.

    Args:
      domain: 'dclaw' or 'dkitty'.
      duration: episode length, s (whole control steps).
      **options: `base.TaskOptions` fields (e.g. `action_bounds`).

    Raises:
      ValueError: for an unknown domain or a non-positive duration.
    """
    if domain not in CENTER_POSE:
      raise ValueError(f'no excitation for {domain!r}; one of {DOMAINS}')
    if not (numeric.is_finite(duration) and duration > 0):
      raise ValueError(
        f'duration must be a positive number of s, got {duration!r}'
      )
    arena, robot = _scene(domain)
    joints = len(robot.joints)
    self.FEATURES = {'qpos': joints, 'qvel': joints, 'last_action': joints}
    self.DEFAULT_OBSERVATION_KEYS = ('qpos', 'qvel', 'last_action')
    self._domain = domain
    self._center = np.array(CENTER_POSE[domain], dtype=float)
    self._error = np.zeros(joints)
    scene = base.Scene(
      arena=arena,
      robot=robot,
      control_timestep=CONTROL_TIMESTEP,
      episode_steps=max(1, round(duration / CONTROL_TIMESTEP)),
    )
    super().__init__(scene, base.TaskOptions(**options))
    self._qpos_feature = self._features['qpos']
    self._qvel_feature = self._features['qvel']

  @property
  def domain(self) -> str:
    return self._domain

  @property
  def center_pose(self) -> np.ndarray:
    """The pose the excitation starts from and moves around, rad."""
    return self._center.copy()

  def action_range(self, physics) -> tuple[np.ndarray, np.ndarray]:
    """The joint targets actions can reach (low, high), rad."""
    del physics  # The action map was bound to it when it compiled.
    return self._action_map.low.copy(), self._action_map.high.copy()

  def _initialize_state(self, physics, random_state) -> None:
    del random_state
    physics.bind(self.robot.joints).qpos = self._center
    physics.bind(self.robot.actuators).ctrl = self._center

  def _compute_features(self, physics) -> None:
    self._qpos_feature[:] = self._sensed_qpos
    self._qvel_feature[:] = self._sensed_qvel
    targets = physics.bind(self.robot.actuators).ctrl
    np.subtract(targets, self._robot_qpos, out=self._error)

  def _compute_reward_terms(self) -> dict[str, float]:
    return {'tracking_error_cost': -geometry.norm(self._error)}

  def _compute_score(self) -> float:
    return 0.0

  def _compute_success(self) -> bool:
    return False
