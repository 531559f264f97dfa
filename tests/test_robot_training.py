"""Learning on a robot: `train --device_path`, on the in-process virtual bus.

The bus runs in simulated time here (fast); the real-time figures (control
period jitter, late steps) come from the standalone bus in
benchmarks/robot_training.py.
"""

import dataclasses
import json
import multiprocessing
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip('sbx', reason='needs robel_dm[learn]')
pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')

from robel_dm import recording, suite  # noqa: E402
from robel_dm.learning import (  # noqa: E402
  actor,
  agents,
  demos,
  learner,
  replay,
  robot_training,
  safety,
)
from robel_dm.learning import training as train_lib  # noqa: E402
from tests import child_signals, test_telemetry  # noqa: E402

# Pose runs 80 steps per episode; learning starts at 500 steps.
CONFIG = train_lib.RunConfig(
  domain='dclaw', task='pose_fixed', steps=700, eval_every=640,
  eval_episodes=1,
)  # fmt: skip
_VIRTUAL_BUS = suite.RobotOptions('virtual')
VIRTUAL = robot_training.RobotRunOptions(_VIRTUAL_BUS)


def _rows(path: pathlib.Path) -> list[dict]:
  return [json.loads(line) for line in path.read_text().splitlines()]


def _recorded_steps(directory: pathlib.Path) -> int:
  return sum(len(e) - 1 for e in recording.read(directory))


def _inject(monkeypatch, on_step) -> list:
  """Calls `on_step(env, n)` before every robot step n of the run."""
  envs = []
  load = robot_training.RobotRunOptions.load

  def load_and_watch(options, config, seed):
    env = load(options, config, seed)
    step, count = env.step, [0]

    def watched(action):
      count[0] += 1
      on_step(env, count[0])
      return step(action)

    env.step = watched
    envs.append(env)
    return env

  monkeypatch.setattr(robot_training.RobotRunOptions, 'load', load_and_watch)
  return envs


def _uniform_action_steps(monkeypatch, *, after_start: bool) -> list[int]:
  """The robot steps at which a run draws a uniform random action (with
  `after_start`, only those past its learning start, where it should act
  with its actor)."""
  steps = []
  episode = robot_training._RobotRun.episode

  class Watched:
    def __init__(self, rng, run):
      self.rng, self.run = rng, run

    def uniform(self, *args, **kwargs):
      if not after_start or self.run.steps >= self.run.learning_starts:
        steps.append(self.run.steps)
      return self.rng.uniform(*args, **kwargs)

    def __getattr__(self, name):
      return getattr(self.rng, name)

  def watched(run, purpose, policy=None):
    if not isinstance(run.rng, Watched):
      run.rng = Watched(run.rng, run)
    return episode(run, purpose, policy)

  monkeypatch.setattr(robot_training._RobotRun, 'episode', watched)
  return steps


@pytest.mark.slow
def test_a_run_learns_on_the_bus_records_every_step_and_resumes(
  tmp_path, monkeypatch
):
  lines = []
  history = robot_training.train_on_robot(
    CONFIG, VIRTUAL, tmp_path, log=lines.append
  )
  # Evaluated on the robot before learning and at the end.
  assert [row['env_steps'] for row in history][0] == 0
  assert all(row['on_robot'] for row in history)
  assert history[-1]['env_steps'] >= CONFIG.steps
  progress = _rows(tmp_path / robot_training.PROGRESS_LOG)
  steps = progress[-1]['robot_steps']
  assert steps >= CONFIG.steps
  # Every step is in the recording, training and evaluation episodes alike.
  assert _recorded_steps(tmp_path / robot_training.RECORDING) == steps
  episodes = recording.read(tmp_path / robot_training.RECORDING)
  purposes = {e.metadata['purpose'] for e in episodes}
  assert purposes == {'training', 'evaluation'}
  # The learner made one update per transition after the first 500 (it
  # catches up before it stops), in batches of 8.
  counts = json.loads((tmp_path / 'checkpoint.json').read_text())
  assert counts['transitions'] == steps
  assert counts['updates'] == (steps - 500) // 8 * 8
  timing = progress[-1]['timing']
  assert timing['steps'] == progress[-1]['steps'] and timing['late_steps'] == 0
  assert 'period p50 50.0 ms' in lines[-2] or 'period p50 50.0 ms' in lines[-3]
  for name in (train_lib.POLICY, train_lib.BEST_POLICY, train_lib.CHECKPOINT,
               train_lib.CURVE):  # fmt: skip
    assert (tmp_path / name).is_file(), name
  # TensorBoard: the evaluations, the learner's losses and the robot's own.
  tags = test_telemetry.read_events(tmp_path)
  for tag in ('eval/success_rate', 'train/critic_loss', 'train/ent_coef',
              'robot/jitter_p99_ms', 'robot/late_steps', 'robot/faults',
              'robot/resets', 'robot/violations_velocity',
              'robot/updates_per_step', 'robot/updates_per_second',
              'robot/actor_age_s', 'robot/seconds'):  # fmt: skip
    assert tags.get(tag), tag
  # Once learning started, one update per step (the robot kept its pace).
  assert tags['robot/updates_per_step'][-1][1] == pytest.approx(1.0, abs=0.05)
  # --resume refills the replay buffer from the recording and goes on,
  # acting with the restored actor from its first step (never with the
  # random actions of a run that has not started learning).
  random_steps = _uniform_action_steps(monkeypatch, after_start=True)
  more = robot_training.train_on_robot(
    CONFIG.__class__(**{**CONFIG.__dict__, 'steps': steps + 160}),
    VIRTUAL,
    tmp_path,
    resume=True,
    log=lines.append,
  )
  assert f'resuming at robot step {steps}: {steps} recorded' in '\n'.join(lines)
  assert random_steps == []
  # The robot's time (simulated here: 50 ms a step, resets and evaluations
  # included) goes on across the sessions.
  before = history[-1]['robot_seconds']
  assert before >= history[-1]['env_steps'] * 0.05
  assert more[-1]['robot_seconds'] >= before + 160 * 0.05
  assert more[-1]['env_steps'] >= steps + 160
  assert (
    _recorded_steps(tmp_path / robot_training.RECORDING)
    == _rows(tmp_path / robot_training.PROGRESS_LOG)[-1]['robot_steps']
  )


@pytest.mark.slow
def test_on_the_simulated_time_bus_the_robot_keeps_the_learners_pace(
  tmp_path,
):
  # A real robot's control period leaves the learner time for its updates;
  # in simulated time nothing would, so the robot waits for the learner:
  # at the end of every episode past the learning start (500 steps) the
  # learner has made all the updates the steps allow (one per step, in
  # chunks of 8).
  assert VIRTUAL.paced_by_learner
  robot_training.train_on_robot(
    CONFIG, VIRTUAL, tmp_path, log=lambda line: None
  )
  rows = _rows(tmp_path / robot_training.PROGRESS_LOG)
  late = [row for row in rows if row['robot_steps'] > 600]
  assert late
  for row in late:
    assert row['updates'] == (row['robot_steps'] - 500) // 8 * 8, row


@pytest.mark.slow
def test_a_fault_ends_the_episode_and_training_goes_on(tmp_path, monkeypatch):
  def lose_goals(env, n):
    if n == 100:  # In the second training episode.
      env.virtual_bus.faults.lose_next_write(12, 3)

  _inject(monkeypatch, lose_goals)
  config = CONFIG.__class__(**{**CONFIG.__dict__, 'steps': 400})
  lines = []
  robot_training.train_on_robot(config, VIRTUAL, tmp_path, log=lines.append)
  progress = _rows(tmp_path / robot_training.PROGRESS_LOG)
  faulted = [row for row in progress if row['ended'].startswith('fault')]
  assert len(faulted) == 1 and 'motors [12]' in faulted[0]['ended']
  assert progress[-1]['faults'] == 1
  # Training went on after the fault, up to its budget.
  assert progress.index(faulted[0]) < len(progress) - 1
  assert progress[-1]['robot_steps'] >= 400
  episodes = recording.read(tmp_path / robot_training.RECORDING)
  assert [e.metadata['complete'] for e in episodes].count(False) == 1
  assert any('hardware fault' in line for line in lines)
  # A resumed run goes on counting (the fault is not forgotten).
  more = CONFIG.__class__(**{**config.__dict__, 'steps': 480})
  robot_training.train_on_robot(
    more, VIRTUAL, tmp_path, resume=True, log=lines.append
  )
  assert _rows(tmp_path / robot_training.PROGRESS_LOG)[-1]['faults'] == 1


@pytest.mark.slow
def test_a_robot_that_cannot_be_reset_stops_the_run_saved(
  tmp_path, monkeypatch
):
  def unplug(env, n):
    if n == 100:
      env.virtual_bus.faults.set_absent(21)

  envs = _inject(monkeypatch, unplug)
  options = robot_training.RobotRunOptions(_VIRTUAL_BUS, reset_attempts=2)
  with pytest.raises(RuntimeError, match='could not be reset 2 times'):
    robot_training.train_on_robot(
      CONFIG, options, tmp_path, log=lambda line: None
    )
  # Every motor that answers is released (the unplugged one cannot hear).
  servos = envs[0].virtual_bus.servos
  assert not any(s.torque_enabled for s in servos if s.motor_id != 21)
  assert (tmp_path / train_lib.CHECKPOINT).is_file()
  assert _recorded_steps(tmp_path / robot_training.RECORDING) >= 99


@pytest.mark.slow
def test_a_learner_that_dies_stops_the_run_with_the_robot_released(
  tmp_path, monkeypatch
):
  def kill_the_learner(env, n):
    if n == 560:  # Past the learning start, in the seventh episode.
      for child in multiprocessing.active_children():
        os.kill(child.pid, signal.SIGKILL)

  envs = _inject(monkeypatch, kill_the_learner)
  with pytest.raises(RuntimeError, match='the learner process ended'):
    robot_training.train_on_robot(
      CONFIG, VIRTUAL, tmp_path, log=lambda line: None
    )
  assert not any(s.torque_enabled for s in envs[0].virtual_bus.servos)
  # The steps before the learner died are recorded.
  assert _recorded_steps(tmp_path / robot_training.RECORDING) >= 559


@pytest.mark.slow
def test_an_episode_ends_at_the_safety_threshold(tmp_path):
  options = robot_training.RobotRunOptions(_VIRTUAL_BUS, max_violations=50)
  config = CONFIG.__class__(**{**CONFIG.__dict__, 'steps': 300})
  robot_training.train_on_robot(
    config, options, tmp_path, log=lambda line: None
  )
  progress = _rows(tmp_path / robot_training.PROGRESS_LOG)
  early = [row for row in progress if row['ended'].startswith('safety')]
  # Uniform random actions break the velocity limits within a few steps.
  assert early and all(sum(r['violations'].values()) >= 50 for r in early)
  assert all(row['steps'] < 80 for row in early)
  assert progress[-1]['early_ends'] == len(early)


def test_a_robot_evaluation_scores_its_episodes_as_simulation_does(
  tmp_path, monkeypatch
):
  scores = []  # ROBEL's score after each robot step, in order.
  load = robot_training.RobotRunOptions.load

  def load_and_watch(options, config, seed):
    env = load(options, config, seed)
    step = env.step

    def watched(action):
      timestep = step(action)
      scores.append(float(timestep.observation['score']))
      return timestep

    env.step = watched
    return env

  monkeypatch.setattr(robot_training.RobotRunOptions, 'load', load_and_watch)
  config = CONFIG.__class__(**{**CONFIG.__dict__, 'steps': 80})
  history = robot_training.train_on_robot(config, VIRTUAL, tmp_path, log=_quiet)
  # Evaluation episodes count as robot steps: the run is two of them.
  assert len(scores) == 160 and len(history) == 2
  for row, episode in zip(history, (scores[:80], scores[80:]), strict=True):
    # The score of an episode is its mean over the steps (as in
    # `evaluation.episodes`); its last step's is kept beside it.
    assert len(set(episode)) > 1
    assert row['mean_score'] == pytest.approx(np.mean(episode), abs=1e-12)
    assert row['mean_final_score'] == episode[-1]
  progress = _rows(tmp_path / robot_training.PROGRESS_LOG)
  assert [r['score'] for r in progress] == pytest.approx(
    [np.mean(scores[:80]), np.mean(scores[80:])], abs=1e-12
  )
  assert [r['final_score'] for r in progress] == [scores[79], scores[159]]


_KILLABLE = """
import sys
from robel_dm import suite
from robel_dm.learning import robot_training, training
config = training.RunConfig(domain='dclaw', task='pose_fixed', steps=100000,
                         eval_every=100000, eval_episodes=1)
options = robot_training.RobotRunOptions(suite.RobotOptions('virtual'))
robot_training.train_on_robot(config, options, sys.argv[1],
                     log=lambda line: print(line, flush=True))
"""


def _learner_processes(parent: int) -> list[int]:
  """The learner processes `parent` started (Linux /proc)."""
  found = []
  for task in pathlib.Path(f'/proc/{parent}/task').iterdir():
    for child in (task / 'children').read_text().split():
      command = pathlib.Path(f'/proc/{child}/cmdline').read_bytes()
      if b'spawn_main' in command:
        found.append(int(child))
  return found


def _alive(pid: int) -> bool:
  try:
    state = pathlib.Path(f'/proc/{pid}/stat').read_text().split()[2]
  except FileNotFoundError:
    return False
  return state != 'Z'


@pytest.mark.slow
def test_kill_9_loses_nothing_already_recorded_and_resume_goes_on(tmp_path):
  root = pathlib.Path(__file__).resolve().parents[1]
  process = subprocess.Popen(
    [sys.executable, '-c', _KILLABLE, str(tmp_path)],
    cwd=root,
    env={**os.environ, 'MUJOCO_GL': 'egl'},
    stdout=subprocess.PIPE,
    stderr=subprocess.DEVNULL,
    preexec_fn=child_signals.default,
    text=True,
  )
  try:
    for line in process.stdout:  # Wait for the third training episode.
      if line.startswith('episode 4 '):
        break
    time.sleep(1.5)
    learners = _learner_processes(process.pid)
    process.send_signal(signal.SIGKILL)
  finally:
    process.wait(timeout=30)
  # The orphaned learner saves and exits (a hang guard of 60 s).
  assert len(learners) == 1
  deadline = time.monotonic() + 60
  while _alive(learners[0]):
    assert time.monotonic() < deadline, 'the orphaned learner still runs'
    time.sleep(0.2)
  recorded = _recorded_steps(tmp_path / robot_training.RECORDING)
  assert recorded >= 240
  lines = []
  config = CONFIG.__class__(**{**CONFIG.__dict__, 'steps': recorded + 80})
  robot_training.train_on_robot(
    config, VIRTUAL, tmp_path, resume=True, log=lines.append
  )
  assert f'resuming at robot step {recorded}: {recorded} recorded' in lines[0]
  assert _recorded_steps(tmp_path / robot_training.RECORDING) >= recorded + 80


@pytest.mark.slow
def test_an_evaluation_cut_short_is_made_again_on_resume(tmp_path, monkeypatch):
  config = CONFIG.__class__(**{**CONFIG.__dict__, 'eval_every': 320})
  evaluate, calls = robot_training._RobotRun.evaluate, []

  def killed_in_the_second(run, policy):
    calls.append(run.steps)
    if len(calls) == 2:  # One episode of it, then the kill.
      run.episode('evaluation', policy)
      raise KeyboardInterrupt
    return evaluate(run, policy)

  monkeypatch.setattr(
    robot_training._RobotRun, 'evaluate', killed_in_the_second
  )
  with pytest.raises(KeyboardInterrupt):
    robot_training.train_on_robot(
      config, VIRTUAL, tmp_path, log=lambda line: None
    )
  monkeypatch.setattr(robot_training._RobotRun, 'evaluate', evaluate)
  cut = calls[1]
  assert cut >= 320
  history = robot_training.train_on_robot(
    config, VIRTUAL, tmp_path, resume=True, log=lambda line: None
  )
  # The cut evaluation is made first thing: before any training episode.
  assert [row['env_steps'] for row in history][:2] == [0, cut + 80]


@pytest.mark.slow
@pytest.mark.parametrize(
  'signum, to_group',
  [(signal.SIGTERM, False), (signal.SIGTERM, True), (signal.SIGQUIT, True)],
)
def test_a_stop_signal_says_what_was_saved_and_how_to_resume(
  tmp_path, signum, to_group
):
  # To the group (a service manager's stop, `kill -- -PGID`, Ctrl-\ in a
  # terminal), the learner gets it too and must still save the networks
  # when the actor asks.
  root = pathlib.Path(__file__).resolve().parents[1]
  output = tmp_path / 'run'
  process = subprocess.Popen(
    [sys.executable, '-m', 'robel_dm.commands.train', '--domain=dclaw',
     '--task=pose_fixed', '--device_path=virtual', '--steps=100000',
     '--eval_every=100000', f'--output_dir={output}'],
    cwd=root,
    env={**os.environ, 'MUJOCO_GL': 'egl'},
    stdout=subprocess.PIPE,
    stderr=subprocess.PIPE,
    preexec_fn=child_signals.default,
    process_group=0,
    text=True,
  )  # fmt: skip
  try:
    for line in process.stdout:  # Wait for a training episode.
      if line.startswith('episode 2 '):
        break
    if to_group:
      os.killpg(process.pid, signum)
    else:
      process.send_signal(signum)
    _, stderr = process.communicate(timeout=120)
  finally:
    if process.poll() is None:
      process.kill()
  assert process.returncode == 128 + signum
  name = signal.Signals(signum).name
  assert f'stopped by {name}: the robot is released (torque off)' in stderr
  assert f'in {output}; the same command with --resume continues' in stderr
  assert (output / train_lib.CHECKPOINT).is_file()
  # Saved at the stop, with the transitions it had (not only the empty
  # checkpoint of the start).
  counts = json.loads(
    (output / train_lib.CHECKPOINT).with_suffix('.json').read_text()
  )
  assert counts['transitions'] > 0


@pytest.mark.slow
def test_learning_starts_from_a_recording(tmp_path):
  # A recording made elsewhere (here: the reference controller, simulated).
  from robel_dm import evaluation  # noqa: PLC0415

  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 2, policy='reference', record=str(tmp_path / 'r')
    )
  )
  config = train_lib.RunConfig(
    domain='dclaw', task='pose_fixed', steps=16, eval_every=16,
    eval_episodes=1, from_recording=(str(tmp_path / 'r'),),
  )  # fmt: skip
  train_lib.train(config, tmp_path / 'run', log=lambda line: None)
  import pickle  # noqa: PLC0415

  with open(tmp_path / 'run' / train_lib.REPLAY_BUFFER, 'rb') as file:
    buffer = pickle.load(file)
  # The 2 x 80 recorded transitions, then the run's own 16: full.
  assert buffer.buffer_size == 160 + 16 and buffer.full
  recorded = [e.steps['action'][1:] for e in recording.read(tmp_path / 'r')]
  np.testing.assert_allclose(
    buffer.actions[:160, 0], np.concatenate(recorded), rtol=1e-6
  )


@pytest.mark.parametrize(
  'options, config, message',
  [
    (robot_training.RobotRunOptions(_VIRTUAL_BUS, hours=0), CONFIG,
     'hours must be > 0'),
    (robot_training.RobotRunOptions(_VIRTUAL_BUS), CONFIG.__class__(
      domain='dclaw', task='pose_fixed', algo='ppo'), 'must be one of'),
    (robot_training.RobotRunOptions(_VIRTUAL_BUS, max_violations=0), CONFIG,
     'max_violations must be >= 1'),
    (robot_training.RobotRunOptions(_VIRTUAL_BUS, updates_per_step=0), CONFIG,
     'updates_per_step must be in'),
    (robot_training.RobotRunOptions(suite.RobotOptions('/dev/ttyUSB9'),
      dynamics='claw_a.json'), CONFIG, '--dynamics calibrates a simulated'),
    (robot_training.RobotRunOptions(_VIRTUAL_BUS), dataclasses.replace(
      CONFIG, task='pose_random_dynamics',
      task_kwargs={'privileged': 'dynamics'}), 'only a simulation knows'),
  ],
)  # fmt: skip
def test_bad_robot_options_are_refused_before_the_robot_moves(
  tmp_path, options, config, message
):
  with pytest.raises(ValueError, match=message):
    robot_training.train_on_robot(config, options, tmp_path, log=print)
  # Nothing written: the corrected command runs.
  assert not any(tmp_path.iterdir())


def test_a_bare_model_file_cannot_start_a_robot_run(tmp_path):
  # Its action map and valve are in the run's config.json, not in the
  # model: without it, the robot could act through another map.
  source = tmp_path / 'copied'
  source.mkdir()
  (source / 'checkpoint.zip').write_bytes(b'')
  config = dataclasses.replace(CONFIG, init_from=str(source / 'checkpoint.zip'))
  output = tmp_path / 'run'
  with pytest.raises(ValueError, match='no config.json beside the model'):
    robot_training.train_on_robot(config, VIRTUAL, output, log=print)
  assert not output.exists()


_AGENT_CHECK = """
import sys
from robel_dm.learning import agents, robot_training, training
for name in sys.argv[1:]:
  sys.modules[name] = None
config = training.RunConfig(domain='dclaw', task='pose_fixed')
try:
  robot_training._check_settings(config, robot_training.RobotRunOptions(
      robot_training.suite.RobotOptions('virtual')))
except ModuleNotFoundError as error:
  print('missing', error.name)
print(*(m for m in ('jax', 'torch', 'sbx') if sys.modules.get(m)))
"""


@pytest.mark.parametrize('missing', [(), ('sbx',), ('torch',)])
def test_a_robot_run_checks_its_agents_packages_without_importing_them(
  missing,
):
  # The learner process imports them; the actor, which drives the robot,
  # starts seconds sooner without them, and still names one that is gone.
  result = subprocess.run(
    [sys.executable, '-c', _AGENT_CHECK, *missing],
    capture_output=True, text=True, check=True,
  )  # fmt: skip
  lines = result.stdout.splitlines()
  assert lines == [*(f'missing {name}' for name in missing), '']


def test_resuming_with_other_robot_options_is_refused(tmp_path):
  (tmp_path / train_lib.CONFIG).write_text(json.dumps(CONFIG.to_json()))
  (tmp_path / robot_training.ROBOT).write_text(
    json.dumps({**VIRTUAL.to_json(), 'max_violations': 5})
  )
  with pytest.raises(ValueError, match='max_violations: 5'):
    robot_training.train_on_robot(CONFIG, VIRTUAL, tmp_path, resume=True)


@pytest.mark.slow
def test_the_command_line_refuses_robot_flags_without_a_robot(tmp_path):
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.train', '--hours=1',
     f'--output_dir={tmp_path}'],
    capture_output=True, text=True, timeout=120,
    env={**os.environ, 'MUJOCO_GL': 'egl'},
  )  # fmt: skip
  assert result.returncode == 2
  assert result.stderr.strip().splitlines()[-1] == (
    'error: --hours needs --device_path (it is about a robot)'
  )


class _FakeLearner:
  """Stands in for the learner process: keeps what the actor sends."""

  def __init__(self, setup):
    rng = np.random.default_rng(0)
    sizes = [setup.observation_size, 8, setup.action_size, setup.action_size]
    self.actor = actor.StochasticActor(
      [(rng.normal(size=(8, sizes[0])), np.zeros(8)),
       (rng.normal(size=(sizes[2], 8)), np.zeros(sizes[2])),
       (rng.normal(size=(sizes[3], 8)), np.zeros(sizes[3]))]
    )  # fmt: skip
    self.updates, self.batches, self.episode_ends = 0, [], []
    _FakeLearner.last = self

  def add(self, batch):
    self.batches.append(batch)

  def end_episode(self, violations):
    self.episode_ends.append(violations)

  def poll(self):
    pass

  def wait_for_actor(self):
    return self.actor

  def wait_until_caught_up(self):
    pass

  def check_alive(self):
    pass

  def request(self, kind):
    pass

  def close(self):
    pass


@pytest.mark.slow
def test_the_agent_learns_from_the_penalized_reward(tmp_path, monkeypatch):
  monkeypatch.setattr(learner, 'Learner', _FakeLearner)
  config = CONFIG.__class__(
    **{**CONFIG.__dict__, 'steps': 160, 'safety_penalty': 2.0}
  )
  robot_training.train_on_robot(
    config, VIRTUAL, tmp_path, log=lambda line: None
  )
  learned = np.concatenate([b.rewards for b in _FakeLearner.last.batches])
  rows = []
  for episode in recording.read(tmp_path / robot_training.RECORDING):
    safety = np.asarray(episode.steps['observation.safety'])[1:].sum(axis=1)
    rows.append(np.asarray(episode.steps['next.reward'])[1:] - 2.0 * safety)
  np.testing.assert_allclose(learned, np.concatenate(rows), rtol=1e-5)
  assert (np.concatenate(rows) != np.concatenate(
    [np.asarray(e.steps['next.reward'])[1:]
     for e in recording.read(tmp_path / robot_training.RECORDING)]
  )).any()  # fmt: skip


@pytest.fixture(scope='module')
def demonstrations(tmp_path_factory):
  """Two episodes of Pose's scripted controller, recorded in simulation."""
  from robel_dm import evaluation  # noqa: PLC0415

  directory = tmp_path_factory.mktemp('demos')
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 2, policy='reference', record=str(directory)
    )
  )
  return str(directory)


@pytest.mark.slow
def test_demonstrations_seed_the_replay_buffer_on_a_robot(
  tmp_path, monkeypatch, demonstrations
):
  monkeypatch.setattr(learner, 'Learner', _FakeLearner)
  config = CONFIG.__class__(
    **{**CONFIG.__dict__, 'algo': 'sac_demos', 'steps': 80,
       'demos': (demonstrations,), 'demo_episodes': 2}
  )  # fmt: skip
  robot_training.train_on_robot(
    config, VIRTUAL, tmp_path, log=lambda line: None
  )
  first = _FakeLearner.last.batches[0]
  assert len(first) == 160  # The demonstrations, before any robot step.
  assert sum(len(batch) for batch in _FakeLearner.last.batches) >= 240


@pytest.mark.slow
def test_behaviour_cloning_uses_the_robot_to_evaluate(tmp_path, demonstrations):
  config = CONFIG.__class__(
    **{**CONFIG.__dict__, 'algo': 'bc', 'steps': 20,
       'demos': (demonstrations,), 'demo_episodes': 2}
  )  # fmt: skip
  history = robot_training.train_on_robot(
    config, VIRTUAL, tmp_path, log=lambda line: None
  )
  assert len(history) == 1 and history[0]['on_robot']
  assert history[0]['epoch'] == 20
  assert (tmp_path / train_lib.BEST_POLICY).is_file()
  assert _recorded_steps(tmp_path / robot_training.RECORDING) == 80


# The command with its training functions replaced by one that prints the
# run's config: what the flags make of a run, without training it.
_COMMAND_CONFIG = """
import dataclasses, json, sys
from absl import app
from robel_dm.commands import train
from robel_dm.learning import robot_training, training

def _print(config, *args, **kwargs):
  print('CONFIG ' + json.dumps(dataclasses.asdict(config)))

robot_training.train_on_robot = training.train = _print
sys.argv = ['train', *sys.argv[1:]]
train._define_flags()
app.run(train.main)
"""


def _command_config(*flags: str) -> dict:
  """The `RunConfig` (as a dict) that `train` with `flags` passes to the
  library, found by running the command with training left out."""
  result = subprocess.run(
    [sys.executable, '-c', _COMMAND_CONFIG, '--domain=dclaw',
     '--task=pose_fixed', '--output_dir=unused', *flags],
    capture_output=True, text=True, timeout=300,
    env={**os.environ, 'MUJOCO_GL': 'egl'},
  )  # fmt: skip
  assert result.returncode == 0, result.stderr[-2000:]
  (line,) = [x for x in result.stdout.splitlines() if x.startswith('CONFIG ')]
  return json.loads(line.removeprefix('CONFIG '))


@pytest.mark.slow
@pytest.mark.parametrize(
  ('flags', 'algo'),
  [
    (['--device_path=virtual'], agents.ROBOT_DEFAULT),
    (['--device_path=virtual', '--algo=sac'], 'sac'),
    ([], agents.DEFAULT),
  ],
)
def test_a_robot_run_learns_with_the_robot_agent_unless_told(flags, algo):
  assert agents.ROBOT_DEFAULT == 'droq' and agents.DEFAULT == 'sac'
  assert _command_config(*flags)['algo'] == algo


# --- Starting from a simulation policy, and a safety budget ----------------


def _quiet(line):
  del line


@pytest.fixture(scope='module')
def simulation_run(tmp_path_factory):
  """A short simulated Pose run of the robot runs' agent (seed 1: networks
  other than a seed-0 run's own)."""
  output = tmp_path_factory.mktemp('simulation')
  train_lib.train(
    CONFIG.__class__(**{**CONFIG.__dict__, 'seed': 1, 'steps': 160,
                        'eval_every': 160}),
    output,
    log=_quiet,
  )  # fmt: skip
  return output


def _observations(episode, keys) -> np.ndarray:
  """An episode's agent vectors, one row per recorded step."""
  return np.concatenate(
    [
      np.asarray(episode.steps[f'observation.{key}'], np.float32).reshape(
        len(episode), -1
      )
      for key in keys
    ],
    axis=1,
  )


@pytest.mark.slow
def test_a_robot_run_acts_with_the_simulation_policy_from_its_first_step(
  tmp_path, monkeypatch, simulation_run
):
  uniform = _uniform_action_steps(monkeypatch, after_start=False)
  config = CONFIG.__class__(
    **{**CONFIG.__dict__, 'steps': 160, 'init_from': str(simulation_run)}
  )
  robot_training.train_on_robot(config, VIRTUAL, tmp_path, log=_quiet)
  # No uniform random action, although learning starts at 500 steps ...
  assert uniform == []
  # ... and no update before it.
  counts = json.loads((tmp_path / 'checkpoint.json').read_text())
  assert counts == {'updates': 0, 'transitions': 240}
  # The first training episode's actions are the source's stochastic
  # actor's, step by step, from the run's random stream.
  source = agents.load(
    config.agent, train_lib.init_checkpoint(str(simulation_run)), None
  )
  policy = actor.StochasticActor(agents.sac_actor_layers(source))
  metadata = json.loads((tmp_path / train_lib.METADATA).read_text())
  assert metadata['init_from'] == str(simulation_run)
  first = next(
    episode
    for episode in recording.read(tmp_path / robot_training.RECORDING)
    if episode.metadata['purpose'] == 'training'
  )
  observations = _observations(first, metadata['observation_keys'])
  rng = np.random.default_rng([config.seed, 0])
  expected = [policy.sample(o, rng) for o in observations[:-1]]
  np.testing.assert_allclose(
    np.asarray(first.steps['action'])[1:], expected, rtol=1e-5, atol=1e-6
  )


@pytest.mark.slow
def test_init_from_a_model_of_other_observations_fails_before_the_robot_moves(
  tmp_path,
):
  turn = tmp_path / 'turn'  # D'Claw Turn: 21 observations, Pose 27.
  train_lib.train(
    train_lib.RunConfig(domain='dclaw', task='turn_fixed', steps=8,
                        eval_every=8, eval_episodes=1),
    turn,
    log=_quiet,
  )  # fmt: skip
  config = CONFIG.__class__(**{**CONFIG.__dict__, 'init_from': str(turn)})
  with pytest.raises(RuntimeError) as raised:
    robot_training.train_on_robot(config, VIRTUAL, tmp_path / 'run', log=print)
  message = str(raised.value)
  assert '\n' not in message
  assert f'--init_from={turn} does not fit this task' in message
  assert 'Observation spaces do not match' in message
  # The robot was never opened: nothing recorded, no episode.
  assert not (tmp_path / 'run' / robot_training.RECORDING).exists()
  assert not (tmp_path / 'run' / robot_training.PROGRESS_LOG).exists()


def test_end_episode_moves_the_multiplier_as_observe_does():
  rng = np.random.default_rng(0)
  episode = rng.integers(0, 4, size=80).astype(np.float32)
  for budget in (0.0, 10.0, 150.0):
    observed = safety.SafetyConstraint(budget, multiplier=0.3)
    ended = safety.SafetyConstraint(budget, multiplier=0.3)
    for t, violations in enumerate(episode):
      observed.observe(np.array([violations]), np.array([t == 79]))
    ended.end_episode(float(episode.sum()))
    assert ended.multiplier == observed.multiplier != 0.3


def _transitions(n, violations=None) -> demos.Transitions:
  return demos.Transitions(
    observations=np.zeros((n, 3), np.float32),
    actions=np.zeros((n, 2), np.float32),
    rewards=np.ones(n, np.float32),
    next_observations=np.zeros((n, 3), np.float32),
    terminals=np.zeros(n, bool),
    episodes=1,
    violations=violations,
  )


def _buffer(size):
  import gymnasium  # noqa: PLC0415
  from stable_baselines3.common.buffers import ReplayBuffer  # noqa: PLC0415

  return ReplayBuffer(
    size,
    gymnasium.spaces.Box(-1, 1, (3,), np.float32),
    gymnasium.spaces.Box(-1, 1, (2,), np.float32),
    device='cpu',
  )


def test_stored_transitions_keep_their_violations():
  buffer = _buffer(6)
  replay.store(buffer, _transitions(2))
  assert getattr(buffer, 'violations', None) is None  # None known yet.
  replay.store(buffer, _transitions(3, np.float32([4, 5, 7])))
  np.testing.assert_array_equal(buffer.violations[:, 0], [0, 0, 4, 5, 7, 0])
  # A full buffer overwrites its oldest rows; those of unknown violations
  # count 0.
  replay.store(buffer, _transitions(4))
  np.testing.assert_array_equal(buffer.violations[:, 0], [0, 0, 0, 5, 7, 0])
  replay.store(buffer, _transitions(1, np.float32([2])))
  np.testing.assert_array_equal(buffer.violations[:, 0], [0, 0, 0, 2, 7, 0])
  # Concatenated: with them, without them, or both (unknown: 0).
  assert demos.concatenate([_transitions(2)] * 2).violations is None
  both = demos.concatenate([_transitions(1), _transitions(2, np.ones(2))])
  np.testing.assert_array_equal(both.violations, [0, 1, 1])
  assert len(both) == 3 and both.episodes == 2


def test_the_learner_moves_the_multiplier_at_each_episode_end(tmp_path):
  import queue  # noqa: PLC0415
  import types  # noqa: PLC0415

  def learning(constraint):
    model = types.SimpleNamespace(replay_buffer=_buffer(10), safety=constraint)
    setup = learner.LearnerSetup('sac', 0, (8,), 3, 2, 10, '', False, 1.0)
    outbox = queue.Queue()
    run = learner._Learning(
      model, setup, (8, 500), tmp_path / 'c.zip', outbox, [0, 0]
    )
    return run, model, outbox

  run, model, outbox = learning(safety.SafetyConstraint(0.0))
  run.handle(('data', _transitions(3, np.float32([5, 6, 9]))))
  np.testing.assert_array_equal(
    model.replay_buffer.violations[:3, 0], [5, 6, 9]
  )
  run.handle(('episode', 20.0))
  expected = safety.SafetyConstraint(0.0)
  expected.end_episode(20.0)
  assert model.safety.multiplier == expected.multiplier > 0
  assert outbox.get_nowait() == (
    'values', {'train/safety_multiplier': expected.multiplier}
  )  # fmt: skip
  # Without a budget an episode's end changes nothing.
  run, model, outbox = learning(None)
  run.handle(('episode', 20.0))
  assert model.safety is None and outbox.empty()


@pytest.mark.slow
def test_the_actor_sends_each_steps_violations_and_each_episodes_total(
  tmp_path, monkeypatch
):
  monkeypatch.setattr(learner, 'Learner', _FakeLearner)
  config = CONFIG.__class__(
    **{**CONFIG.__dict__, 'steps': 160, 'safety_budget': 0.0}
  )
  options = robot_training.RobotRunOptions(_VIRTUAL_BUS, max_violations=40)
  robot_training.train_on_robot(config, options, tmp_path, log=_quiet)
  sent = np.concatenate([b.violations for b in _FakeLearner.last.batches])
  episodes = recording.read(tmp_path / robot_training.RECORDING)
  safety_rows = [
    np.asarray(e.steps['observation.safety'])[1:].sum(axis=1) for e in episodes
  ]
  np.testing.assert_allclose(sent, np.concatenate(safety_rows))
  assert sent.sum() > 0
  # One total per training episode, those cut short by --max_violations
  # too; evaluation episodes move no multiplier.
  rows = _rows(tmp_path / robot_training.PROGRESS_LOG)
  training = [r for r in rows if r['purpose'] == 'training']
  assert any(r['ended'].startswith('safety') for r in training)
  assert _FakeLearner.last.episode_ends == [
    sum(r['violations'].values()) for r in training
  ]


def _multiplier_of(rows: list[dict], budget: float) -> float:
  """The multiplier after the training episodes of progress `rows`."""
  constraint = safety.SafetyConstraint(budget)
  for row in rows:
    if row['purpose'] == 'training' and row['steps']:
      constraint.end_episode(sum(row['violations'].values()))
  return constraint.multiplier


@pytest.mark.slow
def test_a_safety_budget_on_a_robot_learns_its_multiplier_and_resumes_it(
  tmp_path,
):
  from robel_dm.learning import sac  # noqa: PLC0415

  config = CONFIG.__class__(
    **{**CONFIG.__dict__, 'steps': 160, 'safety_budget': 0.0}
  )
  lines = []
  robot_training.train_on_robot(config, VIRTUAL, tmp_path, log=lines.append)
  rows = _rows(tmp_path / robot_training.PROGRESS_LOG)
  saved = sac.SAC.load(str(tmp_path / train_lib.CHECKPOINT)).safety
  # Pose's random actions break the velocity limit: over a budget of 0.
  assert saved.budget == 0.0
  assert saved.multiplier == _multiplier_of(rows, 0.0) > 0
  # Shown: in the progress rows and lines, and in TensorBoard.
  assert rows[-1]['safety_multiplier'] == saved.multiplier
  assert f'multiplier {saved.multiplier:.3g}' in lines[-2]
  assert test_telemetry.read_events(tmp_path).get('train/safety_multiplier')
  # The recording, read back on --resume, carries each step's violations.
  keys = tuple(json.loads((tmp_path / train_lib.METADATA).read_text())[
    'observation_keys'])  # fmt: skip
  recorded = robot_training._recorded(tmp_path, config, keys)
  np.testing.assert_allclose(
    recorded.violations,
    np.concatenate([
      np.asarray(e.steps['observation.safety'])[1:].sum(axis=1)
      for e in recording.read(tmp_path / robot_training.RECORDING)
    ]),
  )  # fmt: skip
  assert recorded.violations.sum() > 0
  # A resumed run goes on from the saved multiplier (one more training
  # episode moves it further).
  robot_training.train_on_robot(
    CONFIG.__class__(**{**config.__dict__, 'steps': 320}),
    VIRTUAL,
    tmp_path,
    resume=True,
    log=lines.append,
  )
  rows = _rows(tmp_path / robot_training.PROGRESS_LOG)
  resumed = sac.SAC.load(str(tmp_path / train_lib.CHECKPOINT)).safety
  assert sum(r['purpose'] == 'training' for r in rows) == 2
  assert resumed.multiplier == _multiplier_of(rows, 0.0) > saved.multiplier


def test_robot_runs_default_to_the_safe_map_and_a_budget():
  safe = robot_training.with_safe_defaults(CONFIG)
  assert safe.task_kwargs == {**CONFIG.task_kwargs, 'action_map': 'safe'}
  assert safe.budget == robot_training.ROBOT_SAFETY_BUDGET == 10.0
  # What the run names stays.
  named = dataclasses.replace(
    CONFIG, task_kwargs={'action_map': 'robel'}, safety_budget=50.0
  )
  kept = robot_training.with_safe_defaults(named)
  assert kept.task_kwargs == {'action_map': 'robel'}
  assert kept.budget == 50.0
  penalized = dataclasses.replace(CONFIG, safety_penalty=1.0)
  assert robot_training.with_safe_defaults(penalized).safety_budget is None
  # Behaviour cloning learns no price: the map only.
  cloned = dataclasses.replace(CONFIG, algo='bc', demos=('demos',))
  assert robot_training.with_safe_defaults(cloned).safety_budget is None


@pytest.mark.slow
@pytest.mark.parametrize('flag', [None, '--nosafe_defaults'])
def test_the_command_line_applies_the_safe_defaults_on_a_robot(flag):
  saved = _command_config('--device_path=virtual', *([flag] if flag else []))
  if flag is None:
    assert saved['task_kwargs'] == {'action_map': 'safe'}
    assert saved['safety_budget'] == 10.0
  else:
    assert saved['task_kwargs'] == {}
    assert saved['safety_budget'] is None
