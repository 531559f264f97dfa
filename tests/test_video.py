"""Episodes as videos: one frame per control step, from a named camera."""

import mujoco
import numpy as np
import pytest

from robel_dm import policies, robots, suite, video

imageio_ffmpeg = pytest.importorskip(
  'imageio_ffmpeg', reason='needs robel_dm[video]'
)


def _frames_in(path) -> int:
  reader = imageio_ffmpeg.read_frames(str(path))
  meta = next(reader)
  count = sum(1 for _ in reader)
  assert meta['size'] == (320, 240)
  return count


@pytest.mark.slow
def test_an_episode_becomes_a_video_with_a_frame_per_step(tmp_path):
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  policy = policies.make_policy('zero', env, seed=0)
  path = tmp_path / 'turn.mp4'
  timestep, frames = video.record_episode(
    env, policy, path, camera='front', size=(240, 320)
  )
  assert timestep.last()
  assert frames == env.task.episode_steps + 1
  assert _frames_in(path) == frames
  env.close()


@pytest.mark.slow
def test_the_goal_marker_is_in_the_picture():
  # The turn task's goal marker is green: a fixed-goal frame has green
  # pixels, and hiding the marker removes them.
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  env.reset()

  def green_pixels():
    frame = video.render(env, 'closeup', (240, 320)).astype(int)
    red, green, blue = frame[..., 0], frame[..., 1], frame[..., 2]
    return int(((green > 150) & (red < 100) & (blue < 100)).sum())

  shown = green_pixels()
  goal = env.task.arena.goal_body.full_identifier
  body = env.physics.model.name2id(goal, 'body')
  mocap = env.physics.model.body_mocapid[body]
  env.physics.data.mocap_pos[mocap] = (0.0, 0.0, -5.0)  # Out of view.
  env.physics.forward()
  # 80 green pixels before the marker was thickened and lit; 206 after.
  assert shown > 150 and green_pixels() < shown / 10
  env.close()


def _segmentation(env, camera, size=(240, 320)):
  return env.physics.render(
    *size, camera_id=video.resolve_camera(env, camera), segmentation=True
  )


def _geoms(env, segmentation, wanted):
  """Pixels showing a geom for which `wanted(name)` holds."""
  model = env.physics.model
  names = [model.id2name(i, 'geom') or '' for i in range(model.ngeom)]
  table = np.array([wanted(name) for name in names] + [False])
  is_geom = segmentation[..., 1] == mujoco.mjtObj.mjOBJ_GEOM
  return table[np.where(is_geom, segmentation[..., 0], -1)]


@pytest.fixture
def kitty():
  env = suite.load('dkitty', 'walk_fixed', seed=0)
  env.reset()
  yield env
  env.close()


@pytest.mark.slow
def test_the_default_dkitty_camera_frames_the_robot(kitty):
  camera = robots.ROBOTS['dkitty'].default_camera
  robot = _geoms(kitty, _segmentation(kitty, camera), _is_kitty)
  # The robot covered 0.34% of the picture in `overview`, the old default
  # (about 40 px tall); 2.8% in `follow`.
  assert robot.mean() > 0.015


@pytest.mark.slow
def test_the_robot_stands_out_from_the_floor_from_above(kitty):
  segmentation = _segmentation(kitty, 'tracking_top')
  robot = _geoms(kitty, segmentation, _is_kitty)
  floor = _geoms(kitty, segmentation, lambda name: name == 'floor')
  luma = video.render(kitty, 'tracking_top', (240, 320)) @ [0.3, 0.59, 0.11]
  differs = np.abs(luma[robot] - np.median(luma[floor])) > 40
  # 22% of the robot's pixels stood out from the near-white floor; 92% do.
  assert robot.any() and differs.mean() > 0.7


def _is_kitty(name):
  return name.startswith('dkitty/')


@pytest.mark.slow
def test_unknown_cameras_are_named():
  env = suite.load('dkitty', 'walk_fixed', seed=0)
  env.reset()
  with pytest.raises(video.VideoError, match='overview'):
    video.check_camera(env, 'nope')
  assert 'overview' in video.camera_names(env)
  assert isinstance(video.render(env, 'overview', (64, 64)), np.ndarray)
  env.close()


@pytest.mark.slow
def test_evaluate_writes_a_video_per_episode(tmp_path):
  from robel_dm import evaluation  # noqa: PLC0415

  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dkitty', 'stand_fixed', 2, policy='zero', video_dir=str(tmp_path)
    )
  )
  paths = [record['video'] for record in results['records']]
  assert len(set(paths)) == 2
  for path, record in zip(paths, results['records'], strict=True):
    reader = imageio_ffmpeg.read_frames(path)
    next(reader)
    assert sum(1 for _ in reader) == record['steps'] + 1


@pytest.mark.slow
def test_cameras_answer_to_their_documented_names():
  # xml/README.md names the kitty's top camera `tracking_top`; the model
  # calls it `dkitty/tracking_top`.
  env = suite.load('dkitty', 'walk_fixed', seed=0)
  env.reset()
  assert 'tracking_top' not in video.camera_names(env)
  assert video.resolve_camera(env, 'tracking_top') == 'dkitty/tracking_top'
  assert video.render(env, 'tracking_top', (32, 32)).shape == (32, 32, 3)
  env.close()


def test_a_render_that_fails_leaves_no_file(tmp_path):
  # evaluate --video opens the writer, then renders the first frame; without
  # a GL backend that render fails, and no (invalid) MP4 may stay behind.
  def failing_render():
    raise video.VideoError('offscreen rendering failed')

  path = tmp_path / 'never.mp4'
  writer = video.VideoWriter(path, fps=10)
  with pytest.raises(video.VideoError):
    writer.add(failing_render())
  writer.close()
  assert not path.exists() and writer.frames == 0
