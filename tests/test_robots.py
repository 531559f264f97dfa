"""Every robot declared in `robel_dm/robots.py` is whole: the layers that
read its declaration find what they need."""

import pytest

from robel_dm import robots, suite
from robel_dm.hardware import config as config_lib

_ROBOTS = sorted(robots.ROBOTS)


@pytest.mark.slow
@pytest.mark.parametrize('name', _ROBOTS)
def test_a_declared_robot_has_tasks_a_scene_a_camera_and_a_configuration(
  name,
):
  robot = robots.ROBOTS[name]
  tasks = suite.TASKS_BY_DOMAIN[name]
  assert tasks, f'{name}: no task registered'
  assert robot.standalone_scene in tasks
  env = suite.load(name, robot.standalone_scene, seed=0)
  cameras = [
    env.physics.model.id2name(i, 'camera')
    for i in range(env.physics.model.ncam)
  ]
  assert any(c.split('/')[-1] == robot.default_camera for c in cameras)
  # The shipped configuration's joints are the model's, in action order.
  configuration = config_lib.default(name)
  assert configuration.robot == name
  assert [m.name for m in configuration.joints] == [
    j.name for j in env.task.robot.joints
  ]
  env.close()


@pytest.mark.parametrize('name', _ROBOTS)
def test_a_declared_robot_names_its_gymnasium_ids(name):
  robel_gym = pytest.importorskip(
    'robel_dm.learning.gym', reason='needs robel_dm[learn]'
  )
  prefix = robots.ROBOTS[name].gym_prefix
  ids = [
    i for i, (domain, _, _) in robel_gym.env_ids().items() if domain == name
  ]
  assert ids and all(i.split('/')[1].startswith(prefix) for i in ids)


def test_the_registry_has_one_entry_per_declared_robot():
  assert sorted(suite.registry.DOMAINS) == _ROBOTS


def test_an_undeclared_robot_has_no_configuration():
  with pytest.raises(config_lib.ConfigError, match="robot 'dhand'"):
    config_lib.default('dhand')
