"""The learner of a run on a robot: a process of its own.

It keeps the replay buffer and the networks (an sbx SAC model), takes the
actor's transitions from a queue, makes at most `updates_per_step` gradient
updates per transition, and sends the actor's weights back a few times a
second; it runs at a lower scheduling priority than the robot's control
loop. `Learner` is its handle in the actor's process; the actor samples
from an `actor.StochasticActor` (see `robel_dm.learning.robot_training`).
"""

import contextlib
import dataclasses
import json
import multiprocessing
import os
import pathlib
import queue
import signal
import time

import numpy as np

from robel_dm.learning import agents, demos, extra, replay, run_files
from robel_dm.learning.actor import StochasticActor
from robel_dm.learning.safety import SafetyConstraint

try:
  import gymnasium
except ImportError as error:  # The optional learn extra.
  raise extra.missing(error) from error

# The learner sends actor weights at most this often, s.
_PUBLISH_INTERVAL = 0.2
# The learner's scheduling priority below the actor's (Unix niceness).
_LEARNER_NICENESS = 10
# Updates a stopping learner still makes to catch up, at most.
_STOP_UPDATES = 2_000
# How long a stopping learner may take to save, s.
_STOP_TIMEOUT = 120.0


@dataclasses.dataclass(frozen=True)
class LearnerSetup:
  """What the learner process builds (picklable).

  Attributes:
    init_from: a saved model (or the run folder holding it) the networks
      start from when the run has no checkpoint of its own yet
      (`agents.warm_start`); None: new networks.
    safety_budget: the safety violations per episode the agent learns to
      stay under (a `SafetyConstraint`); None: no budget.
  """

  algo: str
  seed: int
  layers: tuple[int, ...]
  observation_size: int
  action_size: int
  buffer_size: int
  checkpoint: str
  resume: bool
  updates_per_step: float
  init_from: str | None = None
  safety_budget: float | None = None


class InitFromError(ValueError):
  """An --init_from model made for other observations or actions."""


class _Spaces(gymnasium.Env):
  """A stand-in environment with the task's spaces (never stepped)."""

  def __init__(self, observation_size: int, action_size: int):
    self.observation_space = gymnasium.spaces.Box(
      -np.inf, np.inf, (observation_size,), np.float32
    )
    self.action_space = gymnasium.spaces.Box(
      -1.0, 1.0, (action_size,), np.float32
    )

  def reset(self, *, seed=None, options=None):  # pragma: no cover
    raise NotImplementedError('the learner never steps an environment')

  def step(self, action):  # pragma: no cover
    raise NotImplementedError('the learner never steps an environment')


def learner_main(setup: LearnerSetup, inbox, outbox, progress) -> None:
  """The learner process: replay buffer in, actor weights out.

  Messages in: ('data', demos.Transitions) to store; ('episode', total)
  a training episode ended with `total` safety violations (moves a safety
  budget's multiplier); ('save',) write the checkpoint; ('stop',) save
  and end. Out: ('actor', layers, updates),
  ('saved', updates), ('stopped', updates), ('error', text), ('values',
  {name: value}) (the agent's latest logged values). `progress`
  (two shared integers): the transitions for which it has made every
  update they allow, and its updates so far.
  """
  try:
    # Ctrl-C, Ctrl-\, a closed terminal and a service manager's stop reach
    # the whole process group: the actor decides when the learner stops
    # (after saving), not the signal. Should the actor die, the learner
    # notices (`_learn`) and ends.
    for signum in (
      signal.SIGINT,
      signal.SIGTERM,
      signal.SIGHUP,
      signal.SIGQUIT,
    ):
      signal.signal(signum, signal.SIG_IGN)
    # The robot's control loop wins any contest for a CPU.
    os.nice(_LEARNER_NICENESS)
    agents.single_thread()
    from stable_baselines3.common.logger import Logger  # noqa: PLC0415
    from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

    env = DummyVecEnv(
      [lambda: _Spaces(setup.observation_size, setup.action_size)]
    )
    checkpoint = pathlib.Path(setup.checkpoint)
    model = _model(setup, env, checkpoint)
    # A loaded model's buffer is empty: the recording refills it.
    replay.grow(model, setup.buffer_size)
    model.set_logger(Logger(folder=None, output_formats=[]))
    chunk = int(model.gradient_steps)
    starts = int(model.learning_starts)
    _learn(model, setup, (chunk, starts), checkpoint, (inbox, outbox),
           progress)  # fmt: skip
  except InitFromError as error:  # A setting, not a bug: one line.
    outbox.put(('error', str(error)))
  except BaseException as error:  # noqa: BLE001 (reported to the actor)
    outbox.put(('error', f'{type(error).__name__}: {error}'))
    outbox.cancel_join_thread()  # The actor may be gone: never hang.
    raise


def _model(setup: LearnerSetup, env, checkpoint: pathlib.Path):
  """The learner's model: the run's own checkpoint when it resumes from
  one, else the networks of `setup.init_from`, else new ones; under the
  run's safety budget if it has one (a resumed model keeps its own, with
  its multiplier).

  Raises:
    InitFromError: `setup.init_from` was made for other observations or
      actions.
  """
  agent = agents.get(setup.algo)
  if setup.resume and checkpoint.is_file():
    model = agents.load(agent, checkpoint, env)
  elif setup.init_from is not None:
    source = run_files.init_checkpoint(setup.init_from)
    try:
      model = agents.warm_start(
        agent, source, env, setup.seed, setup.buffer_size
      )
    except ValueError as error:
      raise InitFromError(
        f'--init_from={setup.init_from} does not fit this task: {error}'
      ) from error
  else:
    model = agents.build(
      agent, env, setup.seed, setup.layers, setup.buffer_size
    )
  if setup.safety_budget is not None and model.safety is None:
    model.safety = SafetyConstraint(setup.safety_budget)
  return model


def _learn(model, setup, schedule, checkpoint, queues, progress) -> None:
  """Learns from the transitions the inbox brings until told to stop.

  Args:
    model: the agent (its replay buffer ready for `setup.buffer_size`).
    setup: the LearnerSetup.
    schedule: (updates per chunk, transitions before the first update).
    checkpoint: where the model is saved (its counts beside it, .json).
    queues: (inbox, outbox), as in `learner_main`.
    progress: the two shared integers of `learner_main`.
  """
  inbox, outbox = queues
  learning = _Learning(model, setup, schedule, checkpoint, outbox, progress)
  parent = os.getppid()
  learning.publish_first()
  while True:
    ready = learning.ready()
    # Waits for data when there is nothing to learn yet.
    message = _receive(inbox, wait=not ready)
    if message is None and os.getppid() != parent:
      learning.abandon()  # The actor was killed: keep what we have.
      return
    while message is not None:
      if learning.handle(message):
        return
      message = _receive(inbox, wait=False)
    if ready:
      learning.update()


def _receive(inbox, wait: bool):
  """The inbox's next message, or None if none came.

  Args:
    inbox: the learner's inbox.
    wait: whether to wait for one (up to 1 s) rather than only look.
  """
  try:
    return inbox.get(timeout=1.0) if wait else inbox.get_nowait()
  except queue.Empty:
    return None


class _Learning:
  """The learner's model and counts, and what it does with each message.

  Attributes:
    updates: the gradient updates the model has made (a resumed run's
      networks count the checkpoint's).
    seen: the transitions received (into the replay buffer).
  """

  def __init__(self, model, setup, schedule, checkpoint, outbox, progress):
    self._model, self._setup = model, setup
    self._buffer = model.replay_buffer
    self._chunk, self._starts = schedule
    self._checkpoint = checkpoint
    self._outbox, self._progress = outbox, progress
    # Updates already made by the checkpoint's networks (a resumed run's
    # replayed transitions do not earn new ones).
    self._counts = checkpoint.with_suffix('.json')
    self.updates = 0
    if setup.resume and self._counts.is_file():
      self.updates = json.loads(self._counts.read_text())['updates']
    self.seen = 0
    self._published = 0.0  # When actor weights last went out.

  def publish_first(self) -> None:
    """Sends the actor as it is first (untrained, or the checkpoint's): the
    robot can act before any update."""
    self._outbox.put(
      ('actor', agents.sac_actor_layers(self._model), self.updates)
    )
    self._published = time.monotonic()

  def ready(self) -> bool:
    """Whether the transitions seen allow another chunk of updates (and
    tells the actor how far the learner has got)."""
    allowed = (self.seen - self._starts) * self._setup.updates_per_step
    ready = self.seen >= self._starts and self.updates + self._chunk <= allowed
    self._progress[1] = self.updates
    if not ready:
      self._progress[0] = self.seen  # An actor that waits for us may go on.
    return ready

  def update(self) -> None:
    """One chunk of updates; the actor weights and the logged values go out
    at most every _PUBLISH_INTERVAL."""
    self._train(1)
    now = time.monotonic()
    if now - self._published >= _PUBLISH_INTERVAL:
      layers = agents.sac_actor_layers(self._model)
      self._outbox.put(('actor', layers, self.updates))
      self._outbox.put(('values', _logged(self._model)))
      self._published = now

  def handle(self, message) -> bool:
    """Acts on one message of the inbox; True once told to stop."""
    kind = message[0]
    if kind == 'data':
      replay.store(self._buffer, message[1])
      self.seen += len(message[1])
    elif kind == 'episode':
      self._end_episode(message[1])
    elif kind == 'save':
      self._save()
      self._outbox.put(('saved', self.updates))
    elif kind == 'stop':
      self._stop()
      return True
    return False

  def _end_episode(self, violations: float) -> None:
    """A training episode's end: a safety budget's multiplier moves by its
    `violations`, and goes to the actor."""
    constraint = self._model.safety
    if constraint is None:
      return
    constraint.end_episode(violations)
    self._outbox.put(
      ('values', {'train/safety_multiplier': constraint.multiplier})
    )

  def abandon(self) -> None:
    """Saves, and lets the process end without handing over what it sent."""
    self._save()
    # Nobody reads the actor weights still queued: exit without waiting
    # to hand them over (the process would hang there for ever).
    self._outbox.cancel_join_thread()

  def _stop(self) -> None:
    # The updates the transitions so far allow, then save: a stopped
    # run's networks have learned from all it saw (a bounded wait).
    allowed = int((self.seen - self._starts) * self._setup.updates_per_step)
    backlog = min(max(allowed - self.updates, 0), _STOP_UPDATES)
    self._train(backlog // self._chunk)
    self._progress[1] = self.updates
    self._save()
    self._outbox.put(('stopped', self.updates))

  def _train(self, chunks: int) -> None:
    for _ in range(chunks):
      self._model.train(
        gradient_steps=self._chunk, batch_size=self._model.batch_size
      )
      self.updates += self._chunk

  def _save(self) -> None:
    self._model.save(str(self._checkpoint))
    counts = {'updates': self.updates, 'transitions': self.seen}
    self._counts.write_text(json.dumps(counts))


def _logged(model) -> dict[str, float]:
  """The agent's values logged since the last call (losses, entropy
  coefficient), taken out of its logger."""
  values = {
    name: float(value)
    for name, value in model.logger.name_to_value.items()
    if name.startswith('train/') and isinstance(value, int | float)
  }
  model.logger.dump()  # No output: this only clears them.
  return values


class Learner:
  """The learner process, seen from the actor."""

  def __init__(self, setup: LearnerSetup):
    context = multiprocessing.get_context('spawn')
    self._inbox = context.Queue()
    self._outbox = context.Queue()
    # Transitions caught up with, updates made (see learner_main).
    self._progress = context.Array('q', 2)
    self._sent = 0
    self._process = context.Process(
      target=learner_main,
      args=(setup, self._inbox, self._outbox, self._progress),
      name='robel_dm-learner',
      daemon=True,
    )
    self._process.start()
    self.actor: StochasticActor | None = None
    # When the actor weights arrived (time.monotonic), and the learner's
    # latest logged values.
    self.actor_since = 0.0
    self.values: dict[str, float] = {}

  @property
  def updates(self) -> int:
    """The gradient updates the learner has made."""
    return int(self._progress[1])

  def add(self, transitions: demos.Transitions) -> None:
    self._inbox.put(('data', transitions))
    self._sent += len(transitions)

  def end_episode(self, violations: float) -> None:
    """Tells the learner a training episode ended, with `violations` safety
    violations in all (after its transitions)."""
    self._inbox.put(('episode', float(violations)))

  def wait_until_caught_up(self, timeout: float = _STOP_TIMEOUT) -> None:
    """Waits until the learner has made every update the transitions sent
    so far allow: a robot in simulated time keeps the pace a learner on a
    real robot keeps, instead of outrunning it."""
    deadline = time.monotonic() + timeout
    checked = time.monotonic()
    while self._progress[0] < self._sent:
      now = time.monotonic()
      if now > deadline:
        raise RuntimeError(
          f'the learner did not catch up within {timeout:.0f} s'
        )
      if now - checked > 0.5:
        self.check_alive()
        checked = now
      time.sleep(0.0002)

  def poll(self) -> None:
    """Takes the newest actor weights sent (never waits)."""
    while True:
      try:
        message = self._outbox.get_nowait()
      except queue.Empty:
        return
      self._handle(message)

  def _handle(self, message) -> str:
    kind = message[0]
    if kind == 'actor':
      self.actor = StochasticActor(message[1])
      self.actor_since = time.monotonic()
    elif kind == 'values':
      self.values = {**self.values, **message[1]}
    elif kind == 'error':
      raise RuntimeError(f'the learner process failed: {message[1]}')
    return kind

  def wait_for_actor(self, timeout: float = _STOP_TIMEOUT) -> 'StochasticActor':
    """The actor's weights, waiting for the learner's first ones."""
    deadline = time.monotonic() + timeout
    while self.actor is None:
      if time.monotonic() > deadline:
        raise RuntimeError(f'the learner sent no actor within {timeout:.0f} s')
      try:
        self._handle(self._outbox.get(timeout=0.5))
      except queue.Empty:
        self.check_alive()
    return self.actor

  def check_alive(self) -> None:
    if not self._process.is_alive():
      self.poll()  # Its error, if it sent one.
      raise RuntimeError(
        f'the learner process ended (exit code {self._process.exitcode})'
      )

  def request(self, kind: str, timeout: float = _STOP_TIMEOUT) -> None:
    """Sends ('save',) or ('stop',) and waits for the answer."""
    self._inbox.put((kind,))
    deadline = time.monotonic() + timeout
    answer = {'save': 'saved', 'stop': 'stopped'}[kind]
    while time.monotonic() < deadline:
      try:
        message = self._outbox.get(timeout=0.5)
      except queue.Empty:
        if not self._process.is_alive():
          raise RuntimeError('the learner process ended') from None
        continue
      if self._handle(message) == answer:
        return
    raise RuntimeError(f'the learner did not {kind} within {timeout:.0f} s')

  def close(self) -> None:
    """Stops the process (it saves first if it still can)."""
    if self._process.is_alive():
      with contextlib.suppress(RuntimeError):  # It may have died.
        self.request('stop')
    self._process.join(timeout=5)
    if self._process.is_alive():  # Stuck: it ignores SIGTERM.
      self._process.kill()
      self._process.join(timeout=5)
