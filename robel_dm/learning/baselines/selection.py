"""Which agent the table recommends for a task and which run it ships.

Both are decisions, so both are made on validation readings (a record's
`validation`), never on the test success the table reports. A record of
protocol 1 has no validation reading: its reported success stands in, and
the report marks such rows.
"""

import collections
from collections.abc import Iterable
import dataclasses
import json
import math
import pathlib
import statistics

from robel_dm.learning import agents, baselines, run_files

# A median over seeds where an unsolved seed counts as "more than the
# budget": infinity sorts after every number.
UNSOLVED = math.inf


def validation_success(row: dict) -> float:
  """The success a decision may look at."""
  return row['validation']['success'] if 'validation' in row else row['success']


def solved_on_validation(row: dict) -> bool:
  """Whether the row's `validation_success` reaches the plan's bar."""
  return validation_success(row) >= baselines.PLAN['solved']


def mean_validation_success(group: Iterable[dict]) -> float:
  """The mean over a group's seeds of `validation_success`."""
  return statistics.fmean(validation_success(row) for row in group)


def validation_score(row: dict) -> float:
  return row['validation']['score'] if 'validation' in row else row['score']


def validation_violations(row: dict) -> float | None:
  """Safety violations per validation episode, all kinds summed; None
  where the record has no such reading. A Fixed task's validation episode
  is its test episode (protocol rule 3), so its record's violations are
  that reading."""
  violations = row.get('validation', {}).get('violations')
  if violations is None and row.get('deterministic'):
    violations = row['violations']
  return None if violations is None else sum(violations.values())


def safely_solved(row: dict) -> bool:
  """Solved on validation within the plan's safe violations per episode."""
  violations = validation_violations(row)
  return (
    solved_on_validation(row)
    and violations is not None
    and violations <= baselines.PLAN['safe_violations']
  )


def training_steps_to_80(row: dict) -> int | None:
  """The env steps to the run's first training evaluation at 80%, those of
  the run it started from included, whatever its test reads; None if no
  evaluation got there."""
  if row['steps_to_80'] is None:
    return None
  before = (row.get('started_from') or {}).get('env_steps', 0)
  return before + row['steps_to_80']


def reached_80_in_source(row: dict) -> bool:
  """Whether a run that starts from another read 80% at its first
  training evaluation: its time to 80% is then the whole source run's,
  and what the run adds costs the rest of it."""
  return bool(row.get('started_from')) and row['steps_to_80'] == 0


def steps_to_80(row: dict, solved=baselines.solved) -> float:
  """`training_steps_to_80` of a row `solved` (by default on its reported
  test success, what the tables show; decisions pass
  `solved_on_validation`); UNSOLVED otherwise, or if no evaluation got
  there."""
  steps = training_steps_to_80(row) if solved(row) else None
  return UNSOLVED if steps is None else steps


def minutes_to_80(row: dict, unit: str) -> float | None:
  """The wall or CPU minutes to 80% of a solved row, those of the run it
  started from included; None if not recorded."""
  return training_minutes_to_80(row, unit) if baselines.solved(row) else None


def training_minutes_to_80(row: dict, unit: str) -> float | None:
  """The wall or CPU minutes to the run's first training evaluation at
  80%, those of the run it started from included, whatever its test
  reads; None if not recorded."""
  if not row.get('minutes_to_80'):
    return None
  return source_minutes(row, unit) + row['minutes_to_80'][unit]


def run_minutes(row: dict, unit: str) -> float:
  """The wall or CPU minutes of a run, those of the run it started from
  included."""
  return source_minutes(row, unit) + row[f'{unit}_minutes']


def source_minutes(row: dict, unit: str) -> float:
  """The wall or CPU minutes of the run the row's run started from (0 if
  it started from scratch)."""
  source = (row.get('started_from') or {}).get('minutes', {})
  return source.get(unit, 0.0)


def median_steps_to_80(group: Iterable[dict], solved=baselines.solved) -> float:
  """The lower median over every seed of `steps_to_80`, unsolved seeds
  counted as UNSOLVED (so it is UNSOLVED unless at least half the seeds
  are solved)."""
  return statistics.median_low(
    sorted(steps_to_80(row, solved) for row in group)
  )


def median_validation_steps_to_80(group: Iterable[dict]) -> float:
  """`median_steps_to_80` of the seeds solved on validation: what a
  decision may read."""
  return median_steps_to_80(group, solved_on_validation)


@dataclasses.dataclass(frozen=True)
class Choice:
  """The recommended agent of a task, the run shipped and why."""

  algo: str
  rows: tuple[dict, ...]
  shipped: dict | None
  why: str


def task_groups(rows: Iterable[dict]) -> dict[tuple, dict[str, list[dict]]]:
  """Records by (domain, task, valve) and then by agent, seeds in order."""
  groups = collections.defaultdict(lambda: collections.defaultdict(list))
  for row in sorted(rows, key=lambda row: row['seed']):
    valve = row['task_kwargs'].get('valve', 'valve3')
    groups[(row['domain'], row['task'], valve)][row['algo']].append(row)
  return groups


def _merit(group: list[dict], seeds: int) -> tuple:
  """Higher is better: every seed of the plan run, seeds solved on
  validation, seeds of them solved safely, mean validation success, fewer
  env steps to 80% (median over seeds), less CPU time."""
  safe = sum(safely_solved(row) for row in group)
  solved = sum(map(solved_on_validation, group))
  mean = mean_validation_success(group)
  cpu = _median_cpu_minutes(group)
  return (
    len(group) >= seeds,
    solved,
    safe,
    mean,
    -median_validation_steps_to_80(group),
    -cpu,
  )


def for_robots(algo: str) -> bool:
  """Whether `algo`'s policies run on a robot: not those whose actor reads
  what only a simulation knows (a ceiling, never recommended)."""
  agent = agents.AGENTS.get(algo)
  return agent is None or agent.privileged != agents.PRIVILEGED_ACTOR


def choose(by_agent: dict[str, list[dict]]) -> Choice:
  """The task's recommended agent (best `_merit` of those `for_robots`) and
  the run shipped (`_shipped`)."""
  seeds = len(baselines.PLAN['seeds'])
  ranked = sorted(
    filter(for_robots, by_agent),
    key=lambda algo: _merit(by_agent[algo], seeds),
    reverse=True,
  )
  algo, group = ranked[0], by_agent[ranked[0]]
  shipped = _shipped([by_agent[other] for other in ranked])
  return Choice(algo, tuple(group), shipped, _why(algo, by_agent, ranked))


def _shipped(groups: list[list[dict]]) -> dict | None:
  """The run whose policy goes on robots, of the agents' `groups` in rank
  order (the first is the recommended agent's): the recommended agent's
  best seed solved safely on validation (highest validation success, then
  score); where it has none, the best such seed of the next agents; where
  no agent has one, the best seed solved on validation, of the first agent
  in rank order that has one; None if none has. Which agent to train and
  which policy to run on a robot are separate questions: a seed solved
  ships even where another agent solves more seeds, or none."""

  def merit(row):
    return validation_success(row), validation_score(row)

  for solved in (safely_solved, solved_on_validation):
    for group in groups:
      chosen = [row for row in group if solved(row)]
      if chosen:
        return max(chosen, key=merit)
  return None


def _why(algo: str, by_agent: dict[str, list[dict]], ranked: list[str]) -> str:
  """Why `algo` is recommended: what its seeds read on validation, which
  of `_merit`'s terms put it ahead of the next agent, and any agent with
  fewer seeds recorded that reads more."""
  text = _why_ahead(algo, by_agent, ranked)
  ours = by_agent[algo]
  mean = mean_validation_success(ours)
  seeds = len(baselines.PLAN['seeds'])
  for other in ranked[1:]:
    group = by_agent[other]
    if len(group) >= seeds:
      continue
    other_mean = mean_validation_success(group)
    if other_mean > mean:
      text += (
        f'; `{other}` reads more ({other_mean:.2f} mean on validation) on '
        f'{len(group)} of {seeds} seeds recorded'
      )
    elif other != ranked[1] and _could_rank_above(group, ours):
      text += (
        f'; `{other}` has {len(group)} of {seeds} seeds recorded, and its '
        'missing seeds could put it first'
      )
  return text


def _could_rank_above(incomplete: list[dict], group: list[dict]) -> bool:
  """Whether an agent with seeds missing, each of them solved within the
  limit, would tie or beat `group` on seeds solved and within the limit."""
  missing = len(baselines.PLAN['seeds']) - len(incomplete)
  solved, other = (
    sum(map(solved_on_validation, g)) for g in (group, incomplete)
  )
  safe, other_safe = (sum(map(safely_solved, g)) for g in (group, incomplete))
  return (other + missing, other_safe + missing) >= (solved, safe)


def _why_ahead(
  algo: str, by_agent: dict[str, list[dict]], ranked: list[str]
) -> str:
  """What `algo`'s seeds read on validation, and the first of `_merit`'s
  terms on which it beats the next agent in `ranked`."""
  group = by_agent[algo]
  solved = sum(map(solved_on_validation, group))
  safe = sum(safely_solved(row) for row in group)
  with_validation = sum('validation' in row for row in group)
  if with_validation == len(group):
    reading = 'validation'
  elif with_validation:
    reading = (
      'validation (a seed recorded under protocol 1 has no validation '
      'reading: its reported success stands in)'
    )
  else:
    reading = 'its reported success (protocol 1)'
  text = f'solves {solved} of {len(group)} seeds on {reading}'
  if safe:
    limit = baselines.PLAN['safe_violations']
    text += f', {safe} of them within {limit} violations per episode'
  if len(ranked) < 2:
    others = (
      'the other agents recorded read what only a simulation knows'
      if len(by_agent) > 1
      else 'no other agent recorded'
    )
    return f'{text} ({others})'
  runner_up = by_agent[ranked[1]]
  other_safe = sum(safely_solved(row) for row in runner_up)
  other = sum(map(solved_on_validation, runner_up))
  seeds = len(baselines.PLAN['seeds'])
  incomplete = len(runner_up) < seeds <= len(group)
  # Completeness ranks first, but the reason names it only where it
  # decides: where the runner-up loses on its readings too, they decide.
  if incomplete and _merit(group, seeds)[1:] <= _merit(runner_up, seeds)[1:]:
    return (
      f'{text}; ranked above `{ranked[1]}`, which has {len(runner_up)} of '
      f'{seeds} seeds recorded (agents with every '
      'seed recorded rank first)'
    )
  recorded = _seeds_missing(runner_up, group) if incomplete else ''
  if other < solved:
    return (
      f'{text}; next best `{ranked[1]}` {other} of {len(runner_up)}{recorded}'
    )
  if other_safe < safe:
    return (
      f'{text}; next best `{ranked[1]}` {other} of {len(runner_up)}, '
      f'{other_safe} within the limit{recorded}'
    )
  return f'{text}{_tie_break(group, runner_up, ranked[1])}{recorded}'


def _seeds_missing(runner_up: list[dict], group: list[dict]) -> str:
  """How many seeds the runner-up has, and where its missing seeds could
  not put it above `group` (`_could_rank_above`), that they could not."""
  seeds = len(baselines.PLAN['seeds'])
  text = f' ({len(runner_up)} of {seeds} seeds recorded'
  if not _could_rank_above(runner_up, group):
    text += '; its missing seeds could not put it first'
  return text + ')'


def _median_cpu_minutes(group: list[dict]) -> float:
  """CPU minutes per run, median over seeds, as the tables count them:
  with the run each started from (`run_minutes`)."""
  return statistics.median(run_minutes(row, 'cpu') for row in group)


# `_merit`'s terms after seeds solved and safe: name, reading, format.
_TIE_BREAKS = (
  ('mean validation success', mean_validation_success, '{:.2f}'),
  (
    'env steps to 80% (median over seeds solved on validation)',
    median_validation_steps_to_80,
    '{:,.0f}',
  ),
  ('CPU minutes per run (median over seeds)', _median_cpu_minutes, '{:.1f}'),
)


def _tie_break(group: list[dict], runner_up: list[dict], name: str) -> str:
  """The term after seeds solved (and safe) that puts `group` ahead of
  the next agent's `runner_up` (the last where all before it tie), with
  both readings."""
  tied = ['seeds solved']
  if any(map(safely_solved, group)):
    tied.append('seeds within the limit')
  decisive = next(
    (tie for tie in _TIE_BREAKS if tie[1](group) != tie[1](runner_up)),
    _TIE_BREAKS[-1],
  )
  term, reading, form = decisive
  tied += [tie[0] for tie in _TIE_BREAKS[: _TIE_BREAKS.index(decisive)]]
  ours, theirs = reading(group), reading(runner_up)
  shown = [
    '> budget' if value == UNSOLVED else form.format(value)
    for value in (ours, theirs)
  ]
  ties = ', '.join(tied[:-1]) + ' and ' * (len(tied) > 1) + tied[-1]
  return (
    f'; ties with `{name}` on {ties}, ahead on {term}: {shown[0]} against '
    f'{shown[1]}'
  )


def best_policy(
  domain: str, task: str, rows: list[dict] | None = None
) -> pathlib.Path | None:
  """The policy file of the run `choose` ships for the task (valve3), if
  it is at hand: the run's best policy, or the shipped one if it is that
  run's. Run folders are not committed, so in a fresh clone the shipped
  policy stands until the chosen run is made; without records, too.
  `rows`: the records, if already read."""
  if rows is None:
    results = baselines.RESULTS
    rows = json.loads(results.read_text()) if results.is_file() else []
  shipped = baselines.POLICIES / f'{domain}_{task}.npz'
  metadata = baselines.shipped_metadata(domain, task)
  by_agent = task_groups(rows).get((domain, task, 'valve3'))
  if not by_agent:
    return shipped if metadata else None
  row = choose(by_agent).shipped
  if row is None:
    return None
  run = baselines.Run(domain, task, row['algo'], row['seed'])
  # A run being made again holds a best policy of its own, not its row's.
  best = run.directory / run_files.BEST_POLICY
  if baselines.finished(run) and best.is_file():
    return best
  if metadata and (metadata['algo'], metadata['seed']) == (
    row['algo'],
    row['seed'],
  ):
    return shipped
  return None
