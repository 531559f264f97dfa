"""docs/baselines.md's tables and figures, from docs/baselines.json.

Everything here is derived from the records (`baselines.record`), so the
table, the figures and the data never disagree.
"""

import collections
import hashlib
import json
import shutil
import statistics

import numpy as np

from robel_dm import robots, suite
from robel_dm.learning import baselines, curves
from robel_dm.learning.baselines import selection

START, END = '<!-- table -->', '<!-- /table -->'
SUMMARY_START, SUMMARY_END = '<!-- summary -->', '<!-- /summary -->'
PROGRESS_START, PROGRESS_END = '<!-- progress -->', '<!-- /progress -->'
SOLVED_START, SOLVED_END = '<!-- solved -->', '<!-- /solved -->'


def _name(row: dict) -> str:
  valve = ' (valve4)' if row['task_kwargs'].get('valve') == 'valve4' else ''
  return f'{row["domain"]}/{row["task"]}{valve}'


def _violations(row: dict) -> str:
  # One decimal everywhere: the kinds then add up to the sum shown beside a
  # shipped policy within a tenth, where whole numbers could miss by one.
  return ' / '.join(f'{v:.1f}' for v in row['violations'].values())


def _mean_violations(group: list[dict]) -> str:
  """Test violations per episode by kind (position / velocity / current),
  mean over the group's seeds."""
  kinds = group[0]['violations']
  return ' / '.join(
    f'{statistics.fmean(row["violations"][kind] for row in group):.1f}'
    for kind in kinds
  )


def _steps(value: float) -> str:
  return '> budget' if value == selection.UNSOLVED else f'{value:,.0f}'


def _interval(row: dict) -> tuple[float, float]:
  """The record's 95% interval; for a protocol-1 record, computed from its
  success and episodes."""
  if 'success_interval' in row:
    return tuple(row['success_interval'])
  if row['deterministic']:
    return row['success'], row['success']
  return baselines.interval(row['success'], row['final_episodes'])


def _marks(row: dict) -> str:
  """† a record of an earlier protocol than `baselines.PROTOCOL`; ~ a 95%
  interval that contains the solved rate."""
  marks = '' if row.get('protocol', 1) >= baselines.PROTOCOL else '†'
  low, high = _interval(row)
  if low < baselines.PLAN['solved'] < high:
    marks += '~'
  return marks


def _success(row: dict, label: str = '') -> str:
  """The record's test success and its 95% interval, the interval's
  numbers after `label`."""
  low, high = _interval(row)
  if low == high:
    return f'{row["success"]:.2f}{_marks(row)}'
  return f'{row["success"]:.2f} ({label}{low:.2f}-{high:.2f}){_marks(row)}'


def _validation(row: dict) -> str:
  """The record's validation success and violations per episode (all
  kinds summed) as two cells; '-' where it has no such reading."""
  success = (
    f'{row["validation"]["success"]:.2f}' if 'validation' in row else '-'
  )
  violations = selection.validation_violations(row)
  return f'{success} | {"-" if violations is None else f"{violations:.1f}"}'


def run_table(rows: list[dict]) -> str:
  """One line per run."""
  lines = [
    '| Task | Agent | Seed | Budget | Env steps | Success (95% interval) '
    '| Test episodes | Validation success | Validation violations / '
    'episode | Mean score | Steps to 80% | CPU min to 80% '
    '| Violations / episode (position / velocity / current) '
    '| Wall min | CPU min |',
    '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|',
  ]
  for row in rows:
    episodes = (
      '1 (deterministic)' if row['deterministic'] else row['final_episodes']
    )
    lines.append(
      f'| {_name(row)} | {row["algo"]} | {row["seed"]} '
      f'| {row["budget"]:,} | {row["env_steps"]:,} '
      f'| {_success(row, "95%: ")} '
      f'| {episodes} | {_validation(row)} | {row["score"]:.3f} '
      f'| {_training_steps_to_80(row)} | {_training_minutes_to_80(row)} '
      f'| {_violations(row)} | {_own_minutes(row, "wall")} '
      f'| {_own_minutes(row, "cpu")} |'
    )
  return '\n'.join(lines)


def _own_minutes(row: dict, unit: str) -> str:
  """The run's wall or CPU minutes, and those of the run it started from
  (`sac_warm`, `sac_tight`) beside them, which the per-agent tables add."""
  own = f'{row[f"{unit}_minutes"]:.1f}'
  source = selection.source_minutes(row, unit)
  return f'{own} (+ {source:.1f} source run)' if source else own


def _training_steps_to_80(row: dict) -> str:
  """`selection.training_steps_to_80`, or 'never'."""
  steps = selection.training_steps_to_80(row)
  return 'never' if steps is None else f'{steps:,}'


def _training_minutes_to_80(row: dict) -> str:
  """The CPU minutes to the run's first training evaluation at 80%, those
  of the run it started from included, whatever its test reads; 'never',
  or '-' where the record has no time to 80%."""
  if selection.training_steps_to_80(row) is None:
    return 'never'
  cpu = selection.training_minutes_to_80(row, 'cpu')
  return '-' if cpu is None else f'{cpu:.1f}'


def _spread(group: list[dict]) -> str:
  """Mean success over seeds, the lowest and highest seed, and how many
  seeds carry each mark (in words: a mark beside a mean would read as the
  mean's)."""
  values = [row['success'] for row in group]
  mean = statistics.fmean(values)
  if len(values) == 1:
    return f'{mean:.2f}{_marks(group[0])}'
  cell = f'{mean:.2f} (seeds {min(values):.2f}-{max(values):.2f}'
  meanings = (('~', 'borderline ~'), ('†', 'of an earlier protocol †'))
  for mark, meaning in meanings:
    count = sum(mark in _marks(row) for row in group)
    if count:
      cell += f'; {count} seed{"s" * (count > 1)} {meaning}'
  return cell + ')'


def _per_run(group: list[dict], unit: str) -> str:
  """The median over seeds of a run's wall or CPU minutes (`unit`), the
  whole run (to 80% and on to its stop or budget) and the run it started
  from, if any (`sac_warm`, `sac_tight`: it had to be made first)."""
  minutes = (selection.run_minutes(row, unit) for row in group)
  return f'{statistics.median(minutes):.1f}'


def _median_minutes_to_80(group: list[dict], unit: str) -> str:
  """The median over seeds of the wall or CPU minutes to 80%; unsolved
  seeds count as more than the run."""
  values = sorted(
    selection.minutes_to_80(row, unit)
    if baselines.solved(row) and row.get('minutes_to_80')
    else selection.UNSOLVED
    for row in group
  )
  if any(
    baselines.solved(row) and not row.get('minutes_to_80') for row in group
  ):
    return '-'  # Recorded before the records kept the time to 80%.
  median = statistics.median_low(values)
  return '> budget' if median == selection.UNSOLVED else f'{median:.1f}'


def _in_source(group: list[dict], cell: str) -> str:
  """`cell` (a median to 80%), marked where every solved seed's own run
  read 80% at its first evaluation: the figure is then the length of the
  run it started from, and the agent's own aim (fewer violations, other
  dynamics) costs the rest of the run."""
  solved = [row for row in group if baselines.solved(row)]
  if cell in ('> budget', '-') or not solved:
    return cell
  if all(map(selection.reached_80_in_source, solved)):
    return f"{cell} (its source run's length)"
  return cell


def _steps_to_80(group: list[dict]) -> str:
  return _in_source(group, _steps(selection.median_steps_to_80(group)))


def _cpu_to_80(group: list[dict]) -> str:
  return _in_source(group, _median_minutes_to_80(group, 'cpu'))


def results_table(rows: list[dict], domain: str) -> str:
  """One line per task of a robot: the recommended agent and what it
  gives (`selection.choose`), and the policy shipped."""
  lines = [
    '| Task | Recommended agent (why) | Success: mean over seeds (lowest '
    'and highest seed) | Seeds solved (test) | Env steps to 80% (median) '
    '| CPU min to 80% (median) | CPU min per run (median) '
    '| Violations / episode (pos / vel / cur) | Shipped policy '
    '| Shipped: test success, violations / episode |',
    '|---|---|---|---|---|---|---|---|---|---|',
  ]
  for (dom, task, valve), by_agent in sorted(
    selection.task_groups(rows).items()
  ):
    if dom != domain:
      continue
    choice = selection.choose(by_agent)
    group = list(choice.rows)
    name = task + ('' if valve == 'valve3' else f' ({valve})')
    solved = sum(map(baselines.solved, group))
    shipped, reading = _shipped_cells(
      dom, task, valve, by_agent, choice.shipped
    )
    lines.append(
      f'| {name} | {_agent(choice, by_agent)}: {choice.why}'
      f'{_not_recorded(dom, task, valve, by_agent)} | {_spread(group)} '
      f'| {solved} of {len(group)} '
      f'| {_steps_to_80(group)} '
      f'| {_cpu_to_80(group)} '
      f'| {_per_run(group, "cpu")} '
      f'| {_mean_violations(group)} '
      f'| {shipped} '
      f'| {reading} |'
    )
  return '\n'.join(lines)


def _agent(choice: selection.Choice, by_agent: dict[str, list[dict]]) -> str:
  """The recommended agent; marked as a try, not as an agent that works,
  where none of its seeds solves the task on validation."""
  if any(map(selection.solved_on_validation, choice.rows)):
    return f'`{choice.algo}`'
  if any(
    selection.solved_on_validation(row)
    for algo, rows in by_agent.items()
    if selection.for_robots(algo)
    for row in rows
  ):
    return f'`{choice.algo}` (no seed solved on validation)'
  mean = {
    algo: selection.mean_validation_success(rows)
    for algo, rows in by_agent.items()
    if selection.for_robots(algo)
  }
  most = max(mean, key=mean.get)
  if mean[most] > mean[choice.algo]:
    return (
      f'unsolved on validation (ranked first: `{choice.algo}`; reads most: '
      f'`{most}`)'
    )
  return f'unsolved on validation (ranked first: `{choice.algo}`)'


def _not_recorded(domain: str, task: str, valve: str, by_agent: dict) -> str:
  """The agents for robots the plan runs on the task that have no record
  yet (they could change the choice), as a clause of the reason."""
  missing = sorted(
    {
      run.algo
      for run in baselines.runs()
      if (run.domain, run.task, run.valve4) == (domain, task, valve == 'valve4')
      and run.algo not in by_agent
      and selection.for_robots(run.algo)
    }
  )
  if not missing:
    return ''
  return '; planned, without a record: ' + ', '.join(f'`{a}`' for a in missing)


def _shipped_cells(
  domain: str, task: str, valve: str, by_agent: dict, rule: dict | None
) -> tuple[str, str]:
  """The shipped policy (its file read once): its agent and seed, with
  the rule's run where that differs (its run is not at hand yet); and its
  record's test success (95% interval) and violations per episode, all
  kinds summed. '-' for both if none is shipped."""
  made = baselines.shipped_metadata(domain, task) if valve == 'valve3' else None
  if made is None:
    return '-', '-'
  cell = f'`{made["algo"]}` seed {made["seed"]}'
  if rule is not None and (rule['algo'], rule['seed']) != (
    made['algo'],
    made['seed'],
  ):
    cell += f' (rule: `{rule["algo"]}` seed {rule["seed"]}, not here)'
  record = next(
    row for row in by_agent[made['algo']] if row['seed'] == made['seed']
  )
  violations = sum(record['violations'].values())
  reading = f'{_success(record, "95%: ")}, {violations:.1f}'
  if violations > baselines.PLAN['safe_violations']:
    reading += f' (over {baselines.PLAN["safe_violations"]} violations)'
  return cell, reading


def _by_task_and_agent(rows: list[dict]) -> dict[tuple[str, str], list]:
  """The records grouped by (task name, agent), in record order."""
  groups = collections.defaultdict(list)
  for row in rows:
    groups[(_name(row), row['algo'])].append(row)
  return groups


def summary_table(rows: list[dict]) -> str:
  """One line per task and agent: seeds solved, success, cost."""
  groups = _by_task_and_agent(rows)
  lines = [
    '| Task | Agent | Budget (env steps; bc: epochs) | Seeds solved on '
    f'test (within {baselines.PLAN["safe_violations"]} violations) '
    '| Success: mean over seeds (lowest and highest seed) '
    '| Violations / episode '
    '(pos / vel / cur) | Env steps to 80% (median) '
    '| Wall min per run (median) | CPU min per run (median) |',
    '|---|---|---|---|---|---|---|---|---|',
  ]
  for (name, algo), group in sorted(groups.items()):
    solved = sum(map(baselines.solved, group))
    safe = sum(map(baselines.solved_safely, group))
    budgets = sorted({row['budget'] for row in group})
    lines.append(
      f'| {name} | {algo} | {", ".join(f"{b:,}" for b in budgets)} '
      f'| {solved} of {len(group)} ({safe}) | {_spread(group)} '
      f'| {_mean_violations(group)} '
      f'| {_steps_to_80(group)} '
      f'| {_per_run(group, "wall")} '
      f'| {_per_run(group, "cpu")} |'
    )
  return '\n'.join(lines)


def progress(rows: list[dict]) -> str:
  """How much of the plan the records hold, under which protocol, and
  what they cost."""
  table = baselines.runs()
  default = [r for r in table if r.algo == baselines.PLAN['default_agent']]
  settled = {r.name for r in table if baselines.settled(r)}
  recorded = {
    baselines.Run(
      r['domain'], r['task'], r['algo'], r['seed'],
      r['task_kwargs'].get('valve') == 'valve4',
    ).name
    for r in rows
  }  # fmt: skip
  outside = len(recorded - {r.name for r in table})
  old = sum(row.get('protocol', 1) < baselines.PROTOCOL for row in rows)
  protocols = (
    f'{old} of an earlier protocol, marked †'
    if old
    else f'all of protocol {baselines.PROTOCOL}'
  )
  cpu = sum(row['cpu_minutes'] for row in rows)
  return (
    f'The plan has {len(table)} runs: {len(default)} with the default agent '
    f'(`{baselines.PLAN["default_agent"]}`) and {len(table) - len(default)} '
    f'with the other kinds of agent. Recorded under protocol '
    f'{baselines.PROTOCOL}: {len(settled)} of them, '
    f'{len(settled & {r.name for r in default})} with the default agent. '
    f'`baselines.json` holds {len(rows)} records ({outside} of them runs '
    f'outside the plan, kept for comparison; {protocols}), {cpu:,.0f} CPU '
    'minutes of training in all.'
  )


def remaining(rows: list[dict]) -> str:
  """What the runs still to do cost at most: the steps left of their
  budgets, at the median CPU time per env step of the same agent on the
  same task and valve (its records, and its runs in progress), else on
  the same robot, else anywhere (else of the same kind of agent): an env
  step of Walk RandomDynamics, on its bumps, costs a multiple of Pose's."""
  from robel_dm.learning import agents  # noqa: PLC0415

  def keys(algo: str, domain: str, task: str, task_kwargs: dict) -> tuple:
    kind = agents.get(algo).kind
    variant = baselines.variant(task_kwargs)
    return (algo, domain, task, variant), (algo, domain), algo, kind

  rates = collections.defaultdict(list)  # key -> CPU ms per env step

  def measured(algo, domain, task, kwargs, env_steps, cpu_minutes) -> None:
    if env_steps > 20_000:  # Compilation and evaluation amortized.
      for key in keys(algo, domain, task, kwargs):
        rates[key].append(cpu_minutes * 60_000 / env_steps)

  for row in rows:
    measured(
      row['algo'], row['domain'], row['task'], row['task_kwargs'],
      row['env_steps'], row['cpu_minutes'],
    )  # fmt: skip
  todo = [run for run in baselines.runs() if not baselines.done(run)]
  if not todo:
    return 'No runs to do: every run of the plan is done.'
  done_steps = {}
  for run in todo:
    log = baselines.evaluations(run)  # A run in progress measures its own cost.
    done_steps[run] = log[-1]['env_steps'] if log else 0
    if log:
      measured(
        run.algo, run.domain, run.task, run.task_kwargs,
        log[-1]['env_steps'], log[-1]['cpu_time'] / 60,
      )  # fmt: skip
  steps, minutes = collections.Counter(), collections.Counter()
  for run in todo:
    if agents.get(run.algo).kind == agents.IMITATION:  # Epochs, seconds.
      continue
    left = max(run.config().steps - done_steps[run], 0)
    steps[run.algo] += left
    rate = next(
      (rates[key] for key in keys(run.algo, run.domain, run.task,
                                  run.task_kwargs)
       if rates.get(key)),
      None,
    )  # fmt: skip
    if rate:
      minutes[run.algo] += left * statistics.median(rate) / 60_000
  parts = ', '.join(
    f'{steps[algo]:,} env steps of {algo}'
    + (f' ({minutes[algo] / 60:,.1f} CPU h)' if algo in minutes else '')
    for algo in sorted(steps)
  )
  return (
    f'{len(todo)} runs to do: at most {parts or "nothing"} left, at the '
    'median CPU ms per env step of the agent on the same task (its '
    'records and runs in progress; else on the same robot, else any); '
    f'about {sum(minutes.values()) / 60:,.1f} CPU hours at full budgets '
    '(runs solved sooner stop sooner).'
  )


def solved_table(rows: list[dict]) -> str:
  """Per task (the valve tasks on the 4-prong valve too): the agents whose
  policies run on a robot that solve it on every seed of the plan, or the
  best any of them has done."""
  seeds = len(baselines.PLAN['seeds'])
  groups = {
    key: group
    for key, group in _by_task_and_agent(rows).items()
    if selection.for_robots(key[1])
  }
  tasks = [f'{domain}/{task}' for domain, task in suite.ALL_TASKS]
  tasks += [f'{task} (valve4)' for task in baselines.PLAN['valve4']]
  lines = [
    f'| Task | Solved on {seeds} of {seeds} seeds by '
    '| Otherwise, the best agent (success per seed) |',
    '|---|---|---|',
  ]
  for name in sorted(tasks):
    solving, best = [], None
    for (task, algo), group in sorted(groups.items()):
      if task != name:
        continue
      count = sum(map(baselines.solved, group))
      mean = sum(r['success'] for r in group) / len(group)
      if count >= seeds:
        solving.append(f'`{algo}`')
      elif best is None or (count, mean) > best[0]:
        successes = ', '.join(f'{r["success"]:.2f}' for r in group)
        best = ((count, mean), f'`{algo}`: {successes}')
    otherwise = '' if solving else (best[1] if best else 'no run')
    solvers = ', '.join(solving) or 'none'
    lines.append(f'| {name} | {solvers} | {otherwise} |')
  return '\n'.join(lines)


def _replace(text: str, start: str, end: str, body: str) -> str:
  if start not in text or end not in text:
    return f'{text}\n{start}\n{body}\n{end}\n'
  head, rest = text.split(start, 1)
  _, tail = rest.split(end, 1)
  return f'{head}{start}\n{body}\n{end}{tail}'


def figures(rows: list[dict]) -> list[str]:
  """One figure per task: success against env steps per agent."""
  baselines.FIGURES.mkdir(parents=True, exist_ok=True)
  tasks = collections.defaultdict(lambda: collections.defaultdict(list))
  for row in rows:
    if row['algo'] == 'bc':
      continue  # Epochs, not env steps: BC's result is in the tables.
    log = [
      {'env_steps': steps, 'success_rate': success}
      for steps, success in row['curve']
    ]
    tasks[_name(row)][row['algo']].append(log)
  written = []
  for name, runs in sorted(tasks.items()):
    stem = name.replace('/', '_').replace(' (valve4)', '_valve4')
    path = baselines.FIGURES / f'{stem}.png'
    curves.plot_task(runs, path, name, baselines.PLAN['solved'])
    written.append(path.name)
  return written


def _same_policy(a, b) -> bool:
  """Whether two policy files hold the same arrays and metadata (a run
  made again writes the same policy in new zip bytes: it is not copied)."""
  if not b.is_file():
    return False
  with np.load(a) as first, np.load(b) as second:
    return sorted(first.files) == sorted(second.files) and all(
      np.array_equal(first[name], second[name]) for name in first.files
    )


def ship(rows: list[dict]) -> list[str]:
  """Copies the policy of each task's run that `selection.choose` ships,
  where it is at hand, into policies/ (which `--policy=baseline` runs);
  names what is shipped, and the rule's run where that is not at hand."""
  shipped = []
  for (domain, task, valve), by_agent in sorted(
    selection.task_groups(rows).items()
  ):
    if valve != 'valve3':
      continue
    source = selection.best_policy(domain, task, rows)
    target = baselines.POLICIES / f'{domain}_{task}.npz'
    if (
      source is not None
      and source != target
      and not _same_policy(source, target)
    ):
      shutil.copy(source, target)
    made = baselines.shipped_metadata(domain, task)
    if made is None:
      continue
    line = f'{domain}/{task} ({made["algo"]}, seed {made["seed"]}'
    rule = selection.choose(by_agent).shipped
    if source is None and rule is not None:
      name = baselines.Run(domain, task, rule['algo'], rule['seed']).name
      line += (
        f'; the rule ships {rule["algo"]} seed {rule["seed"]}, whose run is '
        f'not here: robel-baselines train --only={name} --force'
      )
    shipped.append(line + ')')
  return shipped


def readme_table(rows: list[dict]) -> str:
  """The README's summary: per task, the recommended agent, its success
  and cost to 80%, and the policy shipped with its own test reading."""
  lines = [
    '| Task | Agent | Success: mean (seeds: lowest-highest) '
    '| Seeds solved (test) '
    '| Env steps to 80% (median) | CPU min to 80% (median) | CPU min per '
    'run (median) | Shipped | Shipped: test success, violations / episode |',
    '|---|---|---|---|---|---|---|---|---|',
  ]
  for (domain, task, valve), by_agent in sorted(
    selection.task_groups(rows).items()
  ):
    if valve != 'valve3':
      continue
    choice = selection.choose(by_agent)
    group = list(choice.rows)
    shipped, reading = _shipped_cells(
      domain, task, valve, by_agent, choice.shipped
    )
    lines.append(
      f'| {domain}/{task} | {_agent(choice, by_agent)} | {_spread(group)} '
      f'| {sum(map(baselines.solved, group))} of {len(group)} '
      f'| {_steps_to_80(group)} '
      f'| {_cpu_to_80(group)} | {_per_run(group, "cpu")} '
      f'| {shipped} | {reading} |'
    )
  return '\n'.join(lines)


def records_digest() -> str:
  """The SHA-256 of docs/baselines.json, which the figures record."""
  return hashlib.sha256(baselines.RESULTS.read_bytes()).hexdigest()


def write() -> None:
  """Ships the chosen policies, then writes every table and figure of
  docs/baselines.md and the README from docs/baselines.json."""
  rows = json.loads(baselines.RESULTS.read_text())
  print('shipped:', ', '.join(ship(rows)) or 'none')
  text = baselines.DOC.read_text() if baselines.DOC.is_file() else ''
  for domain in robots.ROBOTS:
    text = _replace(
      text,
      f'<!-- results {domain} -->',
      f'<!-- /results {domain} -->',
      results_table(rows, domain),
    )
  text = _replace(text, SUMMARY_START, SUMMARY_END, summary_table(rows))
  text = _replace(text, START, END, run_table(rows))
  text = _replace(text, PROGRESS_START, PROGRESS_END, progress(rows))
  text = _replace(text, SOLVED_START, SOLVED_END, solved_table(rows))
  baselines.DOC.write_text(text)
  if baselines.README.is_file():
    readme = baselines.README.read_text()
    baselines.README.write_text(
      _replace(readme, SUMMARY_START, SUMMARY_END, readme_table(rows))
    )
  written = figures(rows)
  (baselines.FIGURES / 'figures.json').write_text(
    json.dumps({'records_sha256': records_digest(), 'figures': written},
               indent=1) + '\n'
  )  # fmt: skip
  print(readme_table(rows))
  print('figures:', ', '.join(written))
