r"""A zoo robot in real time against the transfer table's simulated time.

    MUJOCO_GL=egl python benchmarks/zoo_real_time.py \
        --pairing=dclaw_turn_random/claw_stiff

The transfer table (`robel-zoo evaluate`) runs each shipped policy on each
zoo robot over the in-process virtual bus, in simulated time. This runs one
such pairing again on the standalone virtual bus (`robel-virtual-bus
--dynamics=` the robot's calibration), whose simulated robot advances with
the wall clock, through a real serial port (a pseudo-terminal) and the
same Dynamixel protocol a robot speaks: the same policy, episodes and
episode seeds as the table's record. Printed: both records' success and
violations per episode (all kinds summed); late control steps are logged
as warnings.
"""

import argparse
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
  from robel_dm import evaluation, policies, suite  # noqa: PLC0415
  from robel_dm.hardware import virtual  # noqa: PLC0415
  from robel_dm.zoo import transfer  # noqa: PLC0415

  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--pairing', default='dclaw_turn_random/claw_stiff')
  args = parser.parse_args()
  (pairing,) = transfer.pairings(args.pairing)
  if pairing.robot is None:
    raise SystemExit('--pairing must name a zoo robot, not the simulation')
  table = {(r['policy'], r['robot']): r for r in transfer.load_records()}.get(
    (pairing.policy, pairing.robot_name)
  )
  policy = policies.load(pairing.path, any_variant=True)
  meta = policy.metadata
  domain, task = meta['domain'], transfer.evaluated_task(meta['task'])
  episodes = transfer.EPISODES['fixed' if task.endswith('_fixed') else 'random']
  dynamics = str(pairing.robot.path)
  with virtual.standalone_bus(domain, dynamics=dynamics) as device:
    results = evaluation.evaluate(
      evaluation.EvalConfig(
        domain=domain, task=task, episodes=episodes, policy=policy,
        seed=transfer.SEED, task_kwargs=meta.get('task_kwargs') or None,
        robot=suite.RobotOptions(device),
      )
    )  # fmt: skip
  real_time = {
    'success': results['success_rate'],
    'violations': sum(results['safety'].values()),
  }
  simulated = table and {
    'success': table['success'],
    'violations': sum(table['violations'].values()),
    'commit': table['commit'],
  }
  print(json.dumps({
    'pairing': args.pairing, 'episodes': episodes, 'seed': transfer.SEED,
    'real_time': real_time, 'simulated_time': simulated,
  }, indent=1))  # fmt: skip


if __name__ == '__main__':
  main()
