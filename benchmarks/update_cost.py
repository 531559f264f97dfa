r"""CPU time of one gradient update of the SAC agents, per agent.

    MUJOCO_GL=egl python benchmarks/update_cost.py --agents=sac,droq

Per agent: builds its model on D'Claw Pose Fixed as a training run does
(one CPU thread, the agent's networks and batch size), fills its replay
buffer with `--transitions` transitions of random actions on the task,
then times `--calls` calls of the agent's own update step (`train` with
its `gradient_steps` and `batch_size`, as after every `train_freq` env
steps), after `--warmup` calls that compile it. Prints per agent the CPU
and wall milliseconds per update and per env step (the agent's updates
per env step times the update's), and the ratio of the agents' CPU
milliseconds per update, measured in this run.
"""

import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _filled_model(name: str, transitions: int):
  """The agent's model on Pose Fixed, its buffer holding `transitions`."""
  from stable_baselines3.common.logger import Logger  # noqa: PLC0415
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  from robel_dm.learning import agents, training  # noqa: PLC0415

  agents.single_thread()
  config = training.RunConfig(
    domain='dclaw', task='pose_fixed', algo=name, seed=0, steps=transitions
  )
  env = DummyVecEnv([lambda: training.make_env(config, 0)])
  model = agents.build(config.agent, env, 0, config.layers, transitions)
  model.set_logger(Logger(folder=None, output_formats=[]))
  rng = np.random.default_rng(0)
  observation = env.reset()
  for _ in range(transitions):
    action = rng.uniform(-1, 1, (1, *env.action_space.shape))
    action = action.astype(np.float32)
    after, reward, ended, infos = env.step(action)
    model.replay_buffer.add(observation, after, action, reward, ended, infos)
    observation = after
  return model


def measure(name: str, args) -> dict:
  """CPU and wall ms per update of agent `name`."""
  from robel_dm.learning import agents  # noqa: PLC0415

  model = _filled_model(name, args.transitions)
  updates = int(model.gradient_steps)
  for _ in range(args.warmup):
    model.train(gradient_steps=updates, batch_size=model.batch_size)
  cpu, wall = time.process_time(), time.perf_counter()
  for _ in range(args.calls):
    model.train(gradient_steps=updates, batch_size=model.batch_size)
  cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
  per_step = agents.updates_per_step(agents.get(name))
  count = args.calls * updates
  return {
    'agent': name,
    'updates_per_env_step': per_step,
    'batch_size': int(model.batch_size),
    'cpu_ms_per_update': 1000 * cpu / count,
    'wall_ms_per_update': 1000 * wall / count,
    'cpu_ms_per_env_step': 1000 * cpu / count * per_step,
  }


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--agents', default='sac,droq')
  parser.add_argument('--transitions', type=int, default=2_000)
  parser.add_argument('--warmup', type=int, default=5)
  parser.add_argument('--calls', type=int, default=50)
  args = parser.parse_args()
  rows = [measure(name, args) for name in args.agents.split(',')]
  print(
    'agent            updates/step  batch  CPU ms/update  wall ms/update'
    '  CPU ms/env step'
  )
  for row in rows:
    print(
      f'{row["agent"]:16s} {row["updates_per_env_step"]:12g} '
      f'{row["batch_size"]:6d} {row["cpu_ms_per_update"]:14.2f} '
      f'{row["wall_ms_per_update"]:15.2f} {row["cpu_ms_per_env_step"]:16.2f}'
    )
  base = rows[0]['cpu_ms_per_update']
  for row in rows[1:]:
    ratio = row['cpu_ms_per_update'] / base
    print(f'CPU per update, {row["agent"]} / {rows[0]["agent"]}: {ratio:.2f}')


if __name__ == '__main__':
  main()
