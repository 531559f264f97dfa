"""How the table's runs are scheduled: queues sharing the runs round
robin (one per core, or per machine), or one Ray task per run."""

import pathlib
import time

from robel_dm.learning import agents, baselines
from robel_dm.learning.baselines import (
  Run,
  demonstrations,
  done,
  finished,
  forget,
  in_progress,
  merge_results,
  record,
  recorded,
  select,
  train_run,
)


def make_run(run: Run, log=print) -> dict | None:
  """`train_run` with the run's demonstrations, made first if its agent
  learns from them; None while they, or the run it starts from, cannot be
  made yet."""
  demos = ()
  if agents.get(run.algo).needs_demos and not finished(run):
    source = demonstrations.record(run, log)
    if source is None:
      log(f'{run.name}: waits for a solved policy to demonstrate the task')
      return None
    demos = (source,)
  return train_run(run, log=log, demos=demos)


def _say_recorded(run: Run, log) -> None:
  row = baselines.recorded_row(run)
  log(
    f'{run.name}: recorded (success {row["success"]:.2f}, protocol '
    f'{row.get("protocol", 1)}); --force makes it again'
  )


def train_queue(
  queue: int,
  queues: int,
  pattern: str | None,
  hours: float | None,
  force: bool = False,
) -> None:
  """Runs this queue's share of the table, round robin, resuming; runs
  that wait for demonstrations are tried again after the others. Runs
  chosen by name (`pattern`) that are done are named, or with `force`
  made again from the start."""
  deadline = time.monotonic() + hours * 3600 if hours else None
  log = lambda line: print(line, flush=True)  # noqa: E731
  mine = [r for i, r in enumerate(select(pattern)) if i % queues == queue]
  waiting = []
  for run in mine:
    if deadline and time.monotonic() > deadline:
      print('time budget used up; the rest resumes on the next call')
      return
    if force:
      forget(run)
    elif finished(run) and not recorded(run):  # Its merge was cut short.
      merge_results([record(run)])
      continue
    elif done(run) and not in_progress(run):  # A remake goes on.
      if pattern:
        _say_recorded(run, log)
      continue
    result = make_run(run, log=log)
    if result is None:
      waiting.append(run)
    else:
      merge_results([result])
  for run in waiting:
    if deadline and time.monotonic() > deadline:
      print('time budget used up; the rest resumes on the next call')
      return
    result = make_run(run, log=log)
    if result is not None:
      merge_results([result])


def _remote_train_run(run: Run, plan: dict, runs_dir: pathlib.Path):
  """`make_run` in a Ray worker, with the driver's plan and run folder."""
  # A worker process of its own: its module settings are the driver's.
  baselines.PLAN, baselines.RUNS_DIR = plan, runs_dir
  return make_run(run, log=lambda line: None)


def runs_to_make(pattern: str | None) -> list[Run]:
  """The selected runs not yet recorded or done, and remakes begun."""
  return [
    run
    for run in select(pattern)
    if not done(run) or not recorded(run) or in_progress(run)
  ]


def train_ray(address: str, pattern: str | None) -> list[dict]:
  """Every selected run as a Ray task (one CPU each); the records merged
  into docs/baselines.json as they end. A run that waits for another (its
  demonstrations' source, or the run it starts from) is submitted again
  whenever a run ends, and named if it still waits when none is left.
  `address` 'local' starts a Ray instance on this machine for the call."""
  from robel_dm.evaluation import workers  # noqa: PLC0415

  with workers.ray_session(address) as ray:
    remote = ray.remote(num_cpus=1)(_remote_train_run)
    settings = baselines.PLAN, baselines.RUNS_DIR
    pending = {
      remote.remote(run, *settings): run for run in runs_to_make(pattern)
    }
    records, waiting = [], []
    while pending:
      ready, _ = ray.wait(list(pending))
      for ref in ready:
        run = pending.pop(ref)
        result = ray.get(ref)
        if result is None:
          waiting.append(run)
          continue
        records.append(result)
        merge_results([result])
        print(f'{run.name}: done')
        # What a waiting run waits for may be this one.
        pending.update({remote.remote(w, *settings): w for w in waiting})
        waiting = []
    for run in waiting:
      print(
        f'{run.name}: waits (for demonstrations or the run it starts from; '
        'call again when that is done)'
      )
    return records
