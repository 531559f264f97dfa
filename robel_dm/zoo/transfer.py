"""The transfer table: every shipped policy in simulation and on every zoo
robot, over the Dynamixel protocol.

A policy runs on the task it was trained on; a RandomDynamics policy runs
on its family's Random task (a robot brings its own dynamics: the
simulator's randomization has no place on it). On a zoo robot the task
talks to an in-process virtual bus in simulated time (`device_path=
'virtual'` with the robot's calibration), exactly as to a real robot; a
D'Kitty that falls is stood back up by the simulated person of
`reset='manual'` (its `robots.Robot.unattended_reset`). The same episode
seeds serve the simulation and every robot. Records go to
docs/zoo/transfer.json, one per policy and robot ('simulation' for the
model), and `report` writes the tables of docs/zoo.md from them.
"""

import dataclasses
import fcntl
import fnmatch
import json
import pathlib
import re
from typing import Any

import numpy as np

from robel_dm import (
  assets,
  evaluation,
  policies,
  provenance,
  robots,
  suite,
  zoo,
)

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS = ROOT / 'docs' / 'zoo' / 'transfer.json'
DOC = ROOT / 'docs/zoo.md'
SIMULATION = 'simulation'
# Episode seeds from here on: used by nothing else (training, validation,
# test and demonstration seeds lie below 10,000,000 elsewhere).
SEED = 11_000_000
# Episodes per policy and robot. A Fixed task's episodes differ on a robot
# only through its sensor noise.
EPISODES = {'fixed': 10, 'random': 20}
_SAFETY = ('position', 'velocity', 'current')


@dataclasses.dataclass(frozen=True)
class Pairing:
  """One evaluation of the table: a shipped policy on a robot.

  Attributes:
    policy: the policy file's name without '.npz', e.g. 'dclaw_pose_random'.
    path: the policy file.
    robot: a zoo robot, or None for the simulated model.
  """

  policy: str
  path: pathlib.Path
  robot: zoo.ZooRobot | None

  @property
  def robot_name(self) -> str:
    return SIMULATION if self.robot is None else self.robot.name


def evaluated_task(trained_task: str) -> str:
  """The task a policy runs on a robot: RandomDynamics becomes Random."""
  return re.sub(r'_random_dynamics$', '_random', trained_task)


def pairings(pattern: str | None = None) -> list[Pairing]:
  """Every shipped policy with the simulation and its domain's zoo robots;
  those whose 'policy/robot' matches `pattern` (fnmatch), if given."""
  chosen = []
  for path in sorted(assets.baselines_dir().glob('*.npz')):
    domain = path.stem.split('_')[0]
    for robot in (None, *zoo.robots(domain)):
      pairing = Pairing(path.stem, path, robot)
      name = f'{pairing.policy}/{pairing.robot_name}'
      if pattern is None or fnmatch.fnmatch(name, pattern):
        chosen.append(pairing)
  return chosen


def evaluate_pairing(pairing: Pairing) -> dict[str, Any]:
  """The record of one policy on one robot (or in simulation)."""
  policy = policies.load(pairing.path, any_variant=True)
  meta = policy.metadata
  domain, task = meta['domain'], evaluated_task(meta['task'])
  episodes = EPISODES['fixed' if task.endswith('_fixed') else 'random']
  robot_options = dynamics = None
  if pairing.robot is not None:
    robot_options = suite.RobotOptions(
      'virtual', reset=robots.ROBOTS[domain].unattended_reset
    )
    dynamics = str(pairing.robot.path)
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      domain=domain,
      task=task,
      episodes=episodes,
      policy=policy,
      seed=SEED,
      task_kwargs=meta.get('task_kwargs') or None,
      robot=robot_options,
      dynamics=dynamics,
    )
  )
  successes = [record['success'] for record in results['records']]
  return {
    'policy': pairing.policy,
    'trained_on': f'{domain}/{meta["task"]}',
    'agent': meta.get('algo'),
    'training_seed': meta.get('seed'),
    'task': f'{domain}/{task}',
    'robot': pairing.robot_name,
    'episodes': episodes,
    'seed': SEED,
    'success': results['success_rate'],
    'success_interval': provenance.proportion(successes)['ci95'],
    'violations': {k: results['safety'][k] for k in _SAFETY},
    'commit': provenance.git_revision(),
  }


def _key(record: dict) -> tuple[str, str]:
  return record['policy'], record['robot']


def load_records(path: pathlib.Path = RESULTS) -> list[dict]:
  return json.loads(path.read_text()) if path.is_file() else []


def merge(records: list[dict], path: pathlib.Path = RESULTS) -> None:
  """Adds or replaces records (by policy and robot), atomically; other
  processes wait their turn."""
  path.parent.mkdir(parents=True, exist_ok=True)
  with open(path.with_suffix('.lock'), 'w') as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    merged = {_key(r): r for r in load_records(path)}
    merged.update({_key(r): r for r in records})
    rows = sorted(merged.values(), key=_key)
    partial = path.with_suffix('.partial')
    partial.write_text(json.dumps(rows, indent=1) + '\n')
    partial.replace(path)


def run(
  pattern: str | None = None, shard: int = 0, shards: int = 1, log=print
) -> None:
  """Evaluates this shard's pairings that have no record yet, merging each
  record as it is made (a cut run resumes where it stopped).

  Raises:
    ValueError: if `pattern` matches no pairing.
  """
  done = {_key(r) for r in load_records()}
  chosen = pairings(pattern)
  if not chosen:
    raise ValueError(
      f"--only={pattern} matches no 'policy/robot' pairing (e.g. "
      "'dclaw_pose_*/*')"
    )
  skipped = 0
  for index, pairing in enumerate(chosen):
    if index % shards != shard:
      continue
    if (pairing.policy, pairing.robot_name) in done:
      skipped += 1
      continue
    record = evaluate_pairing(pairing)
    merge([record])
    log(
      f'{pairing.policy} on {pairing.robot_name}: success '
      f'{record["success"]:.2f}, violations per episode '
      f'{sum(record["violations"].values()):.1f}'
    )
  if skipped:
    log(f'{skipped} pairings already recorded')


# --- The tables ------------------------------------------------------------


def _cell(record: dict | None) -> str:
  if record is None:
    return '-'
  return f'{record["success"]:.2f} / {sum(record["violations"].values()):.0f}'


def domain_table(records: list[dict], domain: str) -> str:
  """One domain's table: success / violations per episode (all kinds
  summed) in simulation, the mean and worst over the zoo robots, and on
  each robot."""
  names = [r.name for r in zoo.robots(domain)]
  by_key = {_key(r): r for r in records}
  header = ['Policy (agent)', 'Runs on', 'Simulation', 'Robots: mean',
            'Worst robot', *names]  # fmt: skip
  lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
  shipped = sorted(
    {r['policy'] for r in records if r['task'].split('/')[0] == domain}
  )
  for policy in shipped:
    sim = by_key.get((policy, SIMULATION))
    on_robots = [by_key.get((policy, name)) for name in names]
    present = [r for r in on_robots if r is not None]
    any_record = sim or present[0]
    mean = worst = '-'
    if len(present) == len(names):
      success = np.array([r['success'] for r in present])
      violations = np.array([sum(r['violations'].values()) for r in present])
      mean = f'{success.mean():.2f} / {violations.mean():.0f}'
      lowest = int(np.argmin(success))
      worst = f'{success[lowest]:.2f} ({names[lowest]})'
    row = [f'{any_record["trained_on"]} (`{any_record["agent"]}`)',
           any_record['task'].split('/')[1], _cell(sim), mean, worst,
           *(_cell(r) for r in on_robots)]  # fmt: skip
    lines.append('| ' + ' | '.join(row) + ' |')
  return '\n'.join(lines)


def robots_table() -> str:
  """The zoo's robots and what differs on each (from their files)."""
  lines = ['| Robot | What differs, and why a real robot could be like it |']
  lines.append('|---|---|')
  lines += [f'| {robot.name} | {robot.about} |' for robot in zoo.robots()]
  return '\n'.join(lines)


def _replace_between(text: str, marker: str, content: str) -> str:
  start, end = f'<!-- {marker} -->', f'<!-- /{marker} -->'
  before, rest = text.split(start)
  _, after = rest.split(end)
  return f'{before}{start}\n{content}\n{end}{after}'


def report(records: list[dict] | None = None, doc: pathlib.Path = DOC) -> None:
  """Writes the robots' table and each domain's transfer table between
  their markers in docs/zoo.md."""
  records = load_records() if records is None else records
  text = _replace_between(doc.read_text(), 'robots', robots_table())
  for domain in robots.ROBOTS:
    text = _replace_between(
      text, f'transfer {domain}', domain_table(records, domain)
    )
  doc.write_text(text)
