r"""What training under RandomDynamics does to a policy, on D'Claw Pose.

    MUJOCO_GL=egl python benchmarks/randomdynamics_training.py --seeds=0,1

Per seed, the default agent (`sac`) trains for `--steps` env steps (no
early stop; one evaluation of 10 episodes every 5,000 steps) under three
conditions: `random` (Pose Random), `noise` (Pose Random with
RandomDynamics' observation noise, 0.05) and `random_dynamics` (Pose
RandomDynamics: that noise and randomized damping, friction loss and servo
gain per episode); with `--conditions=asymmetric,privileged`, Pose
RandomDynamics by `sac_asymmetric` (its critics also observe the
episode's randomized dynamics) and by `sac_privileged` (its actor too: a
ceiling no robot policy can reach); with `--conditions=curriculum`, by
`sac_curriculum` (the randomization grows from none to ROBEL's over the
first half of the run). Each run's best and last policies
then play 50 episodes of Pose RandomDynamics and 50 of Pose Random (episode
seeds from 7,000,000, the same for every policy; a privileged policy plays
RandomDynamics only). Printed per run: the training
curve (success of each evaluation) and, per policy and task, success and
mean return. One JSON line per run, also appended to
OUTPUT/results.jsonl.
"""

import argparse
import json
import pathlib
import shutil
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robel_dm import constants  # noqa: E402

CONDITIONS = {  # task, its arguments, agent
  'random': ('pose_random', {}, 'sac'),
  'noise': (
    'pose_random',
    {'observation_noise': constants.OBSERVATION_NOISE_FRACTION},
    'sac',
  ),
  'random_dynamics': ('pose_random_dynamics', {}, 'sac'),
  'asymmetric': ('pose_random_dynamics', {}, 'sac_asymmetric'),
  'privileged': ('pose_random_dynamics', {}, 'sac_privileged'),
  'curriculum': ('pose_random_dynamics', {}, 'sac_curriculum'),
}
EPISODES = 50
EPISODE_SEED = 7_000_000


def run(condition: str, seed: int, steps: int, output: pathlib.Path) -> dict:
  from robel_dm import evaluation, policies  # noqa: PLC0415
  from robel_dm.learning import training  # noqa: PLC0415

  task, task_kwargs, algo = CONDITIONS[condition]
  config = training.RunConfig(
    domain='dclaw', task=task, task_kwargs=task_kwargs, algo=algo,
    seed=seed, steps=steps, eval_every=5_000, eval_episodes=10,
  )  # fmt: skip
  directory = output / f'{condition}_seed{seed}'
  shutil.rmtree(directory, ignore_errors=True)
  start = time.process_time()
  history = training.train(config, directory, log=lambda line: None)
  row = {
    'condition': condition,
    'seed': seed,
    'curve': [h['success_rate'] for h in history],
  }
  for which in ('best', 'last'):
    file = directory / ('policy_best.npz' if which == 'best' else 'policy.npz')
    # A policy of Pose Random plays Pose RandomDynamics too.
    policy = policies.load(file, any_variant=True)
    # A privileged policy reads what only a RandomDynamics task has.
    targets = ('pose_random_dynamics',) + (
      () if policy.privileged else ('pose_random',)
    )
    for target in targets:
      results = evaluation.evaluate(
        evaluation.EvalConfig(
          'dclaw',
          target,
          EPISODES,
          policy=policy,
          seed=EPISODE_SEED,
          task_kwargs=policy.task_kwargs_for(None),
        )  # fmt: skip
      )
      row[f'{which}@{target}'] = {
        'success': results['success_rate'],
        'return': round(results['mean_return'], 1),
      }
  row['cpu_seconds'] = round(time.process_time() - start)
  return row


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--seeds', default='0')
  parser.add_argument('--steps', type=int, default=60_000)
  parser.add_argument('--conditions', default='random,noise,random_dynamics')
  parser.add_argument(
    '--output', default=str(ROOT / 'runs/randomdynamics_training')
  )
  args = parser.parse_args()
  output = pathlib.Path(args.output)
  output.mkdir(parents=True, exist_ok=True)
  for seed in (int(s) for s in args.seeds.split(',')):
    for condition in args.conditions.split(','):
      row = run(condition, seed, args.steps, output)
      print(json.dumps(row), flush=True)
      with open(output / 'results.jsonl', 'a') as file:
        file.write(json.dumps(row) + '\n')


if __name__ == '__main__':
  main()
