r"""Learning on robots in real time: standalone virtual buses, one run each.

    R=benchmarks/robots
    MUJOCO_GL=egl python benchmarks/robot_training.py --kill_at_step=3000 \
        --robots=default,$R/claw_a.json,$R/claw_b.json

Each robot is a standalone virtual bus (`python -m robel_dm.commands.virtual_bus
--driver=sim`, the simulation advancing with the wall clock, so 20 control
steps of Pose take a second as on a claw); `default` is ROBEL's model, a
file is a calibration (another claw of the same design). On each, `train
--device_path=<its pty>` learns D'Claw Pose from scratch, all at the same
time. With --kill_at_step=N, the first robot's run is killed with SIGKILL
early in an episode after N robot steps and resumed with --resume: the
benchmark reports how much wall time of steps the recording had not kept.

Per robot it prints: robot steps to the first evaluation at >= 80% success,
the success of the best policy evaluated afresh on its bus (10 episodes),
the control loop's tick jitter (|period - 50 ms| between the moments it
reads the motors; each episode's p99, median and worst over the episodes),
the jitter of the reads' completion (the recorded motor timestamps: the
ticks plus the bus's reply time), the late steps the trainer counted, the
faults it survived, and the run's wall minutes.
"""

import argparse
import contextlib
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robel_dm import constants, recording  # noqa: E402
from robel_dm.hardware import virtual  # noqa: E402
from robel_dm.learning import baselines  # noqa: E402

PERIOD = constants.CONTROL_TIMESTEP_FAST  # D'Claw Pose's control period, s.
SOLVED = baselines.PLAN['solved']


def _train(device: str, output: pathlib.Path, args, resume: bool):
  command = [
    sys.executable, '-m', 'robel_dm.commands.train', '--domain=dclaw',
    '--task=pose_fixed', f'--device_path={device}', f'--steps={args.steps}',
    f'--eval_every={args.eval_every}', f'--eval_episodes={args.eval_episodes}',
    f'--stop_at_success={SOLVED}', f'--seed={args.seed}',
    f'--output_dir={output}',
    # As measured in docs/robot_training.md: ROBEL's map, no budget.
    '--algo=sac', '--nosafe_defaults',
  ]  # fmt: skip
  if resume:
    command.append('--resume')
  log = open(output.parent / f'{output.name}.log', 'a')  # noqa: SIM115
  return subprocess.Popen(
    command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
    start_new_session=True,
  )  # fmt: skip


def _rows(path: pathlib.Path) -> list[dict]:
  return [json.loads(line) for line in path.read_text().splitlines()]


def _jitter(directory: pathlib.Path) -> tuple[float, float, int]:
  """p50 and p99 of |period - PERIOD| over consecutive recorded steps."""
  jitters = []
  for episode in recording.read(directory):
    stamps = np.asarray(episode.steps['motor.timestamp'], float)[1:]
    jitters.append(np.abs(np.diff(stamps) - PERIOD))
  values = np.concatenate(jitters)
  return *np.percentile(values, [50, 99]), len(values)


def _evaluate(device: str, policy: pathlib.Path, episodes: int) -> float:
  """Success of `policy` over `episodes` on the bus at `device`."""
  output = policy.parent / 'final.json'
  for _ in range(3):  # A loaded machine may miss the bus's first replies.
    result = subprocess.run(
      [sys.executable, '-m', 'robel_dm.commands.evaluate', '--domain=dclaw',
       '--task=pose_fixed', f'--policy={policy}', f'--episodes={episodes}',
       f'--device_path={device}', f'--output={output}'],
      cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    if result.returncode == 0:
      return json.loads(output.read_text())['success_rate']
    print(f'evaluation failed: {result.stderr.strip().splitlines()[-1]}')
  raise RuntimeError(f'{policy} could not be evaluated on {device}')


def _kill_and_resume(name, device, output, args, run) -> tuple[dict, object]:
  """Kills the run with SIGKILL mid-episode once it has made
  `args.kill_at_step` robot steps, then resumes it."""
  progress = output / name / 'progress.jsonl'
  while run.poll() is None:
    rows = _rows(progress) if progress.is_file() else []
    if rows and rows[-1]['robot_steps'] >= args.kill_at_step:
      break
    time.sleep(0.5)
  if run.poll() is not None:
    raise RuntimeError(f'{name} ended before step {args.kill_at_step}')
  time.sleep(1.7)  # Into the next episode.
  os.killpg(run.pid, signal.SIGKILL)
  kill_time = time.time()
  run.wait()
  time.sleep(2)  # The orphaned learner notices and exits.
  episodes = recording.read(output / name / 'recording')
  last = max(float(e.steps['wall_time'][-1]) for e in episodes)
  killed = {
    'robot': name,
    'recorded_steps': sum(len(e) - 1 for e in episodes),
    'seconds_not_recorded': kill_time - last,
  }
  return killed, _train(device, output / name, args, resume=True)


def collect(output: pathlib.Path, devices: dict[str, str], args) -> list:
  """Each robot's row: its learning, a fresh evaluation, its timing."""
  rows = []
  for name, device in devices.items():
    directory = output / name
    log = _rows(directory / 'eval.jsonl')
    progress = _rows(directory / 'progress.jsonl')
    solved = next(
      (row['env_steps'] for row in log if row['success_rate'] >= SOLVED), None
    )
    p50, p99, steps = _jitter(directory / 'recording')
    ticks = [row['timing'] for row in progress if row['timing']]
    tick_p99 = [t['jitter_p99'] for t in ticks if t['steps'] > 1]
    success = _evaluate(
      device, directory / 'policy_best.npz', args.final_episodes
    )
    rows.append({
      'robot': name,
      'robot_steps': progress[-1]['robot_steps'],
      'steps_to_80': solved,
      'final_success': success,
      'final_episodes': args.final_episodes,
      # The loop's ticks (when it reads the motors), per episode.
      'tick_jitter_p99_median_ms': float(np.median(tick_p99)) * 1e3,
      'tick_jitter_p99_max_ms': float(np.max(tick_p99)) * 1e3,
      # When the reads completed (the recorded motor timestamps): the
      # ticks plus the bus's reply time.
      'read_jitter_p50_ms': p50 * 1e3,
      'read_jitter_p99_ms': p99 * 1e3,
      'periods_measured': steps,
      'late_steps': sum(row['timing']['late_steps'] for row in progress
                        if row['timing']),
      'faults': progress[-1]['faults'],
      'wall_minutes': log[-1]['wall_time'] / 60,
      'curve': [[row['env_steps'], row['success_rate'], row['mean_score']]
                for row in log],
    })  # fmt: skip
  return rows


def report(output: pathlib.Path, rows: list, killed: dict) -> None:
  summary = {'robots': rows, 'kill': killed}
  (output / 'summary.json').write_text(json.dumps(summary, indent=1))
  print(f'{"robot":10s} {"steps":>7s} {"to 80%":>7s} {"success":>8s} '
        f'{"tick p99 med/max ms":>20s} {"read p50/p99 ms":>16s} '
        f'{"late":>5s} {"faults":>6s} {"minutes":>7s}')  # fmt: skip
  for row in rows:
    print(
      f'{row["robot"]:10s} {row["robot_steps"]:7d} '
      f'{row["steps_to_80"] or "never"!s:>7s} {row["final_success"]:8.2f} '
      f'{row["tick_jitter_p99_median_ms"]:9.1f} / '
      f'{row["tick_jitter_p99_max_ms"]:8.1f} '
      f'{row["read_jitter_p50_ms"]:7.1f} / {row["read_jitter_p99_ms"]:6.1f} '
      f'{row["late_steps"]:5d} {row["faults"]:6d} {row["wall_minutes"]:7.1f}'
    )
  if killed:
    print(
      f'killed {killed["robot"]} with SIGKILL: {killed["recorded_steps"]} '
      f'steps recorded, the last {killed["seconds_not_recorded"]:.2f} s not'
    )


def plot(rows: list, path: pathlib.Path) -> None:
  """Success and mean score of each robot's evaluations by robot step."""
  import matplotlib  # noqa: PLC0415

  matplotlib.use('Agg')
  from matplotlib import pyplot  # noqa: PLC0415

  figure, axes = pyplot.subplots(1, 2, figsize=(9, 3.4))
  for row in rows:
    steps, success, score = np.asarray(row['curve'], float).T
    axes[0].plot(steps, success, marker='o', label=row['robot'])
    axes[1].plot(steps, score, marker='o', label=row['robot'])
  for axis, name in zip(axes, ('success rate', 'mean score'), strict=True):
    axis.set_xlabel('robot steps (training and evaluation)')
    axis.set_ylabel(name)
    axis.set_ylim(0, 1.05)
    axis.grid(alpha=0.3)
  axes[0].legend(loc='upper left')
  figure.suptitle("D'Claw Pose learned on virtual buses in real time")
  figure.tight_layout()
  figure.savefig(path, dpi=100)


def main() -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--output', default='runs/robots')
  parser.add_argument('--robots', default='default')
  parser.add_argument('--steps', type=int, default=12_000)
  parser.add_argument('--eval_every', type=int, default=1_000)
  parser.add_argument('--eval_episodes', type=int, default=3)
  parser.add_argument('--final_episodes', type=int, default=10)
  parser.add_argument('--seed', type=int, default=0)
  parser.add_argument('--kill_at_step', type=int, default=None)
  args = parser.parse_args()
  os.environ.setdefault('MUJOCO_GL', 'egl')
  output = pathlib.Path(args.output)
  output.mkdir(parents=True, exist_ok=True)
  devices, runs, killed = {}, {}, {}
  # The buses stop when the block ends, after the runs (below).
  with contextlib.ExitStack() as buses:
    try:
      for robot in args.robots.split(','):
        name = pathlib.Path(robot).stem
        dynamics = None if robot == 'default' else robot
        devices[name] = buses.enter_context(
          virtual.standalone_bus('dclaw', dynamics=dynamics)
        )
        runs[name] = _train(devices[name], output / name, args, resume=False)
      if args.kill_at_step:
        first = next(iter(runs))
        killed, runs[first] = _kill_and_resume(
          first, devices[first], output, args, runs[first]
        )
      for run in runs.values():
        run.wait()
      rows = collect(output, devices, args)
      report(output, rows, killed)
      plot(rows, output / 'curves.png')
    finally:
      for run in runs.values():
        if run.poll() is None:
          os.killpg(run.pid, signal.SIGTERM)
  return 0


if __name__ == '__main__':
  sys.exit(main())
