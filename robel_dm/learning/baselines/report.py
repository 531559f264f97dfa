"""docs/baselines.md's tables and figures, from docs/baselines.json.

Everything here is derived from the records (`baselines.record`), so the
table, the figures and the data never disagree.
"""

import collections
import json
import shutil
import statistics

from robel_dm import suite
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
  return ' / '.join(f'{v:.1f}' for v in row['violations'].values())


def run_table(rows: list[dict]) -> str:
  """One line per run."""
  lines = [
    '| Task | Agent | Seed | Env steps | Success | Episodes | Mean score '
    '| Steps to 80% | Violations / episode (position / velocity / current) '
    '| Wall min | CPU min |',
    '|---|---|---|---|---|---|---|---|---|---|---|',
  ]
  for row in rows:
    reached = row['steps_to_80']
    episodes = (
      '1 (deterministic)' if row['deterministic'] else row['final_episodes']
    )
    lines.append(
      f'| {_name(row)} | {row["algo"]} | {row["seed"]} '
      f'| {row["env_steps"]:,} | {row["success"]:.2f} '
      f'| {episodes} '
      f'| {row["score"]:.3f} '
      f'| {"never" if reached is None else f"{reached:,}"} '
      f'| {_violations(row)} | {row["wall_minutes"]:.0f} '
      f'| {row["cpu_minutes"]:.0f} |'
    )
  return '\n'.join(lines)


def _by_task_and_agent(rows: list[dict]) -> dict[tuple[str, str], list]:
  """The records grouped by (task name, agent), in record order."""
  groups = collections.defaultdict(list)
  for row in rows:
    groups[(_name(row), row['algo'])].append(row)
  return groups


def summary_table(rows: list[dict]) -> str:
  """One line per task and agent: seeds solved, success, compute."""
  groups = _by_task_and_agent(rows)
  lines = [
    '| Task | Agent | Seeds solved (success >= 0.8) | Success per seed '
    '| Median steps to 80% | CPU min in all |',
    '|---|---|---|---|---|---|',
  ]
  for (name, algo), group in sorted(groups.items()):
    solved = sum(map(baselines.solved, group))
    reached = sorted(
      row['steps_to_80'] for row in group if row['steps_to_80'] is not None
    )
    median = f'{reached[len(reached) // 2]:,}' if reached else 'never'
    successes = ', '.join(f'{row["success"]:.2f}' for row in group)
    lines.append(
      f'| {name} | {algo} | {solved} of {len(group)} '
      f'| {successes} '
      f'| {median} | {sum(row["cpu_minutes"] for row in group):.0f} |'
    )
  return '\n'.join(lines)


def progress(rows: list[dict]) -> str:
  """How much of the plan the records hold, and what they cost."""
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
  cpu = sum(row['cpu_minutes'] for row in rows)
  return (
    f'The plan has {len(table)} runs: {len(default)} with the default agent '
    f'(`{baselines.PLAN["default_agent"]}`) and {len(table) - len(default)} '
    f'with the other kinds of agent. Settled (recorded, and solved or '
    f"trained to the plan's budget): {len(settled)} of them, "
    f'{len(settled & {r.name for r in default})} with the default agent. '
    f'`baselines.json` holds {len(rows)} records ({outside} of them runs '
    f'outside the plan, kept for comparison), {cpu:,.0f} CPU minutes of '
    f'training in all.'
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
  """Per Fixed and Random task (the valve tasks on the 4-prong valve too):
  the agents that solve it on every seed of the plan, or the best any
  agent has done."""
  seeds = len(baselines.PLAN['seeds'])
  groups = _by_task_and_agent(rows)
  tasks = [f'{domain}/{task}' for domain, task in suite.FIXED + suite.RANDOM]
  tasks += [f'{task} (valve4)' for task in baselines.PLAN['valve4']]
  lines = [
    f'| Task | Solved on {seeds} of {seeds} seeds by '
    '| Otherwise, best so far |',
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
    otherwise = '' if solving else (best[1] if best else 'no run yet')
    lines.append(
      f'| {name} | {", ".join(solving) or "not yet"} | {otherwise} |'
    )
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
    curves.plot_task(runs, path, name)
    written.append(path.name)
  return written


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
    if source is not None and source != target:
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
        f'not here: baselines train --only={name} --force'
      )
    shipped.append(line + ')')
  return shipped


def write() -> None:
  rows = json.loads(baselines.RESULTS.read_text())
  text = baselines.DOC.read_text() if baselines.DOC.is_file() else ''
  text = _replace(text, SUMMARY_START, SUMMARY_END, summary_table(rows))
  text = _replace(text, START, END, run_table(rows))
  text = _replace(text, PROGRESS_START, PROGRESS_END, progress(rows))
  text = _replace(text, SOLVED_START, SOLVED_END, solved_table(rows))
  baselines.DOC.write_text(text)
  print(summary_table(rows))
  print('figures:', ', '.join(figures(rows)))
  print('shipped:', ', '.join(ship(rows)) or 'none')
