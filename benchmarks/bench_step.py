"""Control-step and reset speed of every task against raw MuJoCo.

For each task this measures, in one process and interleaved round by round:
  * `env.step` per control step, driven by a fixed sequence of random actions;
  * the raw ceiling: `mujoco.mj_step(model, data, nstep)` on the same compiled
    model, with `nstep` = physics steps per control step, replaying from the
    same initial state the joint targets the environment sent, so both runs
    simulate the same trajectory (no Python around it but the loop);
  * `env.reset`.
Each figure is the minimum over rounds of the per-round mean (other jobs on a
shared machine only ever add time). Prints a table; `--json` also writes it.

    MUJOCO_GL=egl python benchmarks/bench_step.py [--steps 200] [--rounds 7]
"""

import argparse
import json
import time

import mujoco
import numpy as np

from robel_dm import suite


def _time_env_steps(env, actions, controls) -> float:
  """Times env.step over `actions`; logs the joint targets it sent."""
  step = env.step
  ctrl = env.physics.data.ctrl
  start = time.perf_counter()
  for i, action in enumerate(actions):
    step(action)
    controls[i] = ctrl
  return (time.perf_counter() - start) / len(actions)


def _time_raw_steps(model, data, initial_data, controls, nstep) -> float:
  mujoco.mj_copyData(data, model, initial_data)
  mj_step = mujoco.mj_step
  ctrl = data.ctrl
  start = time.perf_counter()
  for control in controls:
    ctrl[:] = control
    mj_step(model, data, nstep)
  return (time.perf_counter() - start) / len(controls)


def _time_resets(env, count) -> float:
  start = time.perf_counter()
  for _ in range(count):
    env.reset()
  return (time.perf_counter() - start) / count


def bench_task(domain, task, steps, rounds, resets):
  # No time limit: the timed stretch is uninterrupted control steps.
  env = suite.load(domain, task, seed=0, time_limit=float('inf'))
  env.reset()
  physics = env.physics
  model = physics.model.ptr
  data = mujoco.MjData(model)
  initial_data = mujoco.MjData(model)
  nstep = env.task.physics_steps_per_control_step
  rng = np.random.default_rng(0)
  actions = rng.uniform(-1.0, 1.0, (steps,) + env.action_spec().shape)
  controls = np.zeros((steps, model.nu))
  env_times, raw_times, reset_times = [], [], []
  for _ in range(rounds):
    reset_times.append(_time_resets(env, resets))
    mujoco.mj_copyData(initial_data, model, physics.data.ptr)
    env_times.append(_time_env_steps(env, actions, controls))
    raw_times.append(
      _time_raw_steps(model, data, initial_data, controls, nstep)
    )
  env_step, raw_step = min(env_times), min(raw_times)
  return {
    'domain': domain,
    'task': task,
    'substeps': nstep,
    'env_step_us': env_step * 1e6,
    'raw_step_us': raw_step * 1e6,
    'ratio': raw_step / env_step,
    'reset_ms': min(reset_times) * 1e3,
  }


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--steps', type=int, default=200)
  parser.add_argument('--rounds', type=int, default=7)
  parser.add_argument('--resets', type=int, default=20)
  parser.add_argument('--domain', default=None)
  parser.add_argument('--task', default=None, help='only tasks containing this')
  parser.add_argument('--json', default=None, help='write results here')
  args = parser.parse_args()
  rows = []
  header = (
    f'{"task":<28} {"sub":>3} {"env.step us":>11} {"raw us":>8} '
    f'{"raw/env":>7} {"reset ms":>8}'
  )
  print(header)
  print('-' * len(header))
  for domain, task in suite.ALL_TASKS:
    if args.domain and domain != args.domain:
      continue
    if args.task and args.task not in task:
      continue
    row = bench_task(domain, task, args.steps, args.rounds, args.resets)
    rows.append(row)
    print(
      f'{domain + "/" + task:<28} {row["substeps"]:>3} '
      f'{row["env_step_us"]:>11.1f} {row["raw_step_us"]:>8.1f} '
      f'{row["ratio"]:>7.3f} {row["reset_ms"]:>8.3f}',
      flush=True,
    )
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(rows, f, indent=2)


if __name__ == '__main__':
  main()
