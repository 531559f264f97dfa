r"""Trains robel_dm's baselines and writes docs/baselines.md from the runs.

    # Train (two queues, one per core; each run resumes if interrupted):
    MUJOCO_GL=egl python benchmarks/baselines.py train --queue=0 &
    MUJOCO_GL=egl python benchmarks/baselines.py train --queue=1 &
    # Then the table, the curves and the shipped policies:
    MUJOCO_GL=egl python benchmarks/baselines.py report

Every run is SAC with Stable-Baselines3's defaults (256 x 256, learning
rate 3e-4, batch 256, one update per env step, one torch thread), evaluated
every `EVAL_EVERY` env steps on `EVAL_EPISODES` episodes with ROBEL's
reward. `RUNS` lists each run's task, seed, env-step budget and safety
penalty; the budgets were set from the steps each task needed on this
2-core machine.
"""

import argparse
import dataclasses
import json
import pathlib
import shutil

ROOT = pathlib.Path(__file__).resolve().parent.parent
RUNS_DIR = ROOT / 'runs' / 'baselines'
DOCS = ROOT / 'docs/baselines.md'
CURVES_DIR = ROOT / 'docs' / 'baselines'
POLICIES_DIR = ROOT / 'policies'
EVAL_EVERY = 5_000
EVAL_EPISODES = 10
SOLVED = 0.8  # Success rate that counts as solved.


@dataclasses.dataclass(frozen=True)
class Run:
  domain: str
  task: str
  seed: int
  steps: int
  safety_penalty: float = 0.0
  queue: int = 0

  @property
  def name(self) -> str:
    penalty = f'_penalty{self.safety_penalty:g}' if self.safety_penalty else ''
    return f'{self.domain}_{self.task}{penalty}_seed{self.seed}'


RUNS = (
  # Queue 1: the D'Claw's Turn (about 50 min a seed here) and second seeds.
  Run('dclaw', 'turn_fixed', 0, 180_000, queue=1),
  Run('dclaw', 'screw_fixed', 1, 40_000, queue=1),
  Run('dkitty', 'walk_fixed', 1, 50_000, queue=1),
  Run('dclaw', 'turn_fixed', 1, 180_000, queue=1),
  # Queue 0: the rest.
  Run('dclaw', 'pose_fixed', 0, 15_000),
  Run('dkitty', 'stand_fixed', 0, 25_000),
  Run('dclaw', 'pose_fixed', 1, 15_000),
  Run('dkitty', 'stand_fixed', 1, 25_000),
  Run('dclaw', 'pose_fixed', 0, 15_000, safety_penalty=1.0),
  Run('dkitty', 'stand_fixed', 0, 25_000, safety_penalty=1.0),
  Run('dkitty', 'orient_fixed', 0, 40_000),
  Run('dkitty', 'walk_fixed', 0, 50_000),
  Run('dclaw', 'screw_fixed', 0, 40_000),
  Run('dkitty', 'orient_fixed', 1, 40_000),
)


def train(queue: int) -> None:
  from robel_dm import train as train_lib  # noqa: PLC0415

  for run in RUNS:
    if run.queue != queue:
      continue
    output = RUNS_DIR / run.name
    done = output / train_lib.EVAL_LOG
    if done.is_file():
      rows = [json.loads(line) for line in done.read_text().splitlines()]
      if rows and rows[-1]['env_steps'] >= run.steps:
        continue
    resume = (output / train_lib.CHECKPOINT).is_file()
    train_lib.train(
      run.domain,
      run.task,
      output,
      steps=run.steps,
      seed=run.seed,
      eval_every=EVAL_EVERY,
      eval_episodes=EVAL_EPISODES,
      safety_penalty=run.safety_penalty,
      resume=resume,
      log=lambda line: print(line, flush=True),
    )


def _rows(run: Run) -> list[dict]:
  path = RUNS_DIR / run.name / 'eval.jsonl'
  if not path.is_file():
    return []
  return [json.loads(line) for line in path.read_text().splitlines()]


def _summary(run: Run) -> dict | None:
  rows = _rows(run)
  if not rows:
    return None
  last = rows[-1]
  first_solved = next(
    (row['env_steps'] for row in rows if row['success_rate'] >= SOLVED), None
  )
  return {
    'steps': last['env_steps'],
    'success': last['success_rate'],
    'score': last['mean_score'],
    'return': last['mean_return'],
    'safety': last['safety'],
    'first_solved': first_solved,
    'minutes': last['wall_time'] / 60,
    'complete': last['env_steps'] >= run.steps,
  }


def report() -> None:
  CURVES_DIR.mkdir(parents=True, exist_ok=True)
  POLICIES_DIR.mkdir(exist_ok=True)
  lines = []
  shipped = {}
  for run in RUNS:
    summary = _summary(run)
    if summary is None:
      lines.append(
        f'| {run.domain}/{run.task} | {run.seed} | {run.safety_penalty:g} '
        f'| {run.steps:,} | not run | | | | | |'
      )
      continue
    safety = summary['safety']
    solved = summary['first_solved']
    lines.append(
      f'| {run.domain}/{run.task} | {run.seed} | {run.safety_penalty:g} '
      f'| {summary["steps"]:,}{"" if summary["complete"] else " (cut)"} '
      f'| {summary["success"]:.1f} | {summary["score"]:.3f} '
      f'| {safety["position"]:.1f} / {safety["velocity"]:.1f} '
      f'| {f"{solved:,}" if solved else "never"} '
      f'| {summary["minutes"]:.0f} | {summary["return"]:.0f} |'
    )
    curve = RUNS_DIR / run.name / 'learning_curve.png'
    if curve.is_file():
      shutil.copy(curve, CURVES_DIR / f'{run.name}.png')
    best = shipped.get((run.domain, run.task))
    if (
      not run.safety_penalty
      and summary['success'] >= SOLVED
      and (best is None or summary['score'] > best[0])
    ):
      shipped[(run.domain, run.task)] = (summary['score'], run)
  for (domain, task), (_, run) in shipped.items():
    shutil.copy(
      RUNS_DIR / run.name / 'policy.npz', POLICIES_DIR / f'{domain}_{task}.npz'
    )
  table = '\n'.join(lines)
  text = DOCS.read_text() if DOCS.is_file() else ''
  start, end = '<!-- table -->', '<!-- /table -->'
  if start in text and end in text:
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    text = f'{head}{start}\n{HEADER}\n{table}\n{end}{tail}'
    DOCS.write_text(text)
  print(HEADER)
  print(table)
  print(
    'shipped:',
    sorted(f'{d}/{t} (seed {r.seed})' for (d, t), (_, r) in shipped.items()),
  )


HEADER = (
  '| Task | Seed | Safety penalty | Env steps | Success | Mean score '
  '| Violations / episode (position / velocity) | Steps to 80% success '
  '| Minutes | Return |\n|---|---|---|---|---|---|---|---|---|---|'
)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  commands = parser.add_subparsers(dest='command', required=True)
  train_parser = commands.add_parser('train', help='run one queue of RUNS')
  train_parser.add_argument('--queue', type=int, default=0)
  commands.add_parser('report', help='write docs/baselines.md and policies/')
  args = parser.parse_args()
  if args.command == 'train':
    train(args.queue)
  else:
    report()


if __name__ == '__main__':
  main()
