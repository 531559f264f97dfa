"""Demonstrations for the table's bc and sac_demos runs.

A task is demonstrated by its scripted reference controller; where it has
none, by its pinned demonstrator (`docs/baselines/demonstrators/`, one
`<domain>_<task>.npz` per task, committed with the table's data so that
every checkout records the same episodes); else by the table's best solved
policy of the task at hand. The recording is made once per machine under
`runs/baselines/demos/` and made again if its source changes.
"""

import hashlib
import pathlib
import shutil

from robel_dm.evaluation import task_args
from robel_dm.learning import baselines
from robel_dm.learning.baselines import selection

DIRECTORY = baselines.ROOT / 'docs' / 'baselines' / 'demonstrators'


def demonstrator(domain: str, task: str) -> pathlib.Path:
  """Where the task's pinned demonstrator policy is kept (if it has one)."""
  return DIRECTORY / f'{domain}_{task}.npz'


def _source(run: baselines.Run) -> str | None:
  """'reference', a policy file, or None (nothing can demonstrate yet)."""
  if task_args.unavailable('reference', run.domain, run.task, {}) is None:
    return 'reference'
  pinned = demonstrator(run.domain, run.task)
  if pinned.is_file():
    return str(pinned)
  best = selection.best_policy(run.domain, run.task)
  return None if best is None else str(best)


def record(run: baselines.Run, log=print) -> str | None:
  """The demonstration recording for `run` (made if needed, and made again
  if its source changed), or None if nothing can demonstrate the task yet."""
  from robel_dm import evaluation, policies  # noqa: PLC0415

  source = _source(run)
  if source is None:
    return None
  demo_episodes = baselines.PLAN['demo_episodes']
  directory = baselines.RUNS_DIR / 'demos' / f'{run.domain}_{run.task}'
  made_by = directory / 'source.txt'
  # A policy is known by its bytes: a run's best policy can change in place.
  identity = source if source == 'reference' else _sha256(source)
  episodes = directory / 'meta' / 'episodes.jsonl'
  if (
    episodes.is_file()
    and made_by.is_file()
    and made_by.read_text() == identity
    and len(episodes.read_text().splitlines()) >= demo_episodes
  ):
    return str(directory)
  shutil.rmtree(directory, ignore_errors=True)
  directory.parent.mkdir(parents=True, exist_ok=True)
  log(f'demonstrations of {run.domain}/{run.task} by {source}')
  evaluation.evaluate(
    evaluation.EvalConfig(
      run.domain,
      run.task,
      demo_episodes,
      policy=source if source == 'reference' else policies.load(source),
      seed=baselines.DEMO_SEED_OFFSET,
      record=str(directory),
    )
  )
  made_by.write_text(identity)
  return str(directory)


def _sha256(path: str) -> str:
  return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()
