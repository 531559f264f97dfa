"""Stable-Baselines3 models as policy.npz files (`robel_dm.learning.convert`).

The models are untrained (small networks, nothing learned): the conversion
only has to reproduce whatever actor it is given.
"""

import subprocess
import sys

import numpy as np
import pytest

from robel_dm import evaluation, policies

gymnasium = pytest.importorskip('gymnasium', reason='needs robel_dm[learn]')
sb3 = pytest.importorskip('stable_baselines3', reason='needs robel_dm[learn]')
sb3_contrib = pytest.importorskip('sb3_contrib', reason='needs robel_dm[learn]')

from robel_dm.commands import convert as convert_command  # noqa: E402
from robel_dm.learning import convert  # noqa: E402 (after the skips)

POSE = 'robel_dm:robel_dm/DClawPoseFixed-v0'
_SETTINGS = {
  'sac': (sb3.SAC, {'buffer_size': 100}),
  'tqc': (sb3_contrib.TQC, {'buffer_size': 100}),
  'ppo': (sb3.PPO, {'n_steps': 64, 'batch_size': 64}),
}


def _model(tmp_path, algo, env_id=POSE):
  """An untrained `algo` model of the task, saved: its .zip's path."""
  cls, kwargs = _SETTINGS[algo]
  env = gymnasium.make(env_id)
  model = cls(
    'MlpPolicy',
    env,
    seed=0,
    device='cpu',
    policy_kwargs={'net_arch': [32, 32]},
    **kwargs,
  )
  path = tmp_path / f'{algo}.zip'
  model.save(path)
  env.close()
  return path


def _main(capsys, *args):
  code = convert_command.main(list(args))
  captured = capsys.readouterr()
  return code, captured.out, captured.err


@pytest.mark.slow
@pytest.mark.parametrize('algo', ['sac', 'tqc', 'ppo'])
def test_converted_policy_acts_as_the_model(tmp_path, capsys, algo):
  path = _model(tmp_path, algo)
  output = tmp_path / 'policy.npz'
  code, out, err = _main(
    capsys,
    f'--model={path}',
    f'--algo={algo}',
    '--domain=dclaw',
    '--task=pose_fixed',
    f'--output={output}',
  )
  assert code == 0, err
  assert f'wrote {output}' in out
  policy = policies.load(output)
  assert policy.metadata['algo'] == algo
  assert policy.metadata['converted_from'] == f'{algo}.zip'
  model = _SETTINGS[algo][0].load(path, device='cpu')
  env = gymnasium.make(POSE)
  observations = [env.reset(seed=seed)[0] for seed in range(50)]
  rng = np.random.default_rng(1)
  observations = np.concatenate(
    [observations, rng.standard_normal((50, 27)).astype(np.float32)]
  )
  expected, _ = model.predict(observations, deterministic=True)
  np.testing.assert_allclose(policy.act(observations), expected, atol=1e-5)
  results = evaluation.evaluate(
    evaluation.EvalConfig('dclaw', 'pose_fixed', 1, policy=policy)
  )
  assert len(results['records']) == 1


@pytest.mark.slow
def test_a_model_of_another_task_is_refused(tmp_path, capsys):
  path = _model(tmp_path, 'sac')
  with pytest.raises(
    convert.ConvertError,
    match=r'takes 27 observation values, dclaw/turn_fixed gives 21 \(claw',
  ):
    convert.convert(path, 'sac', 'dclaw', 'turn_fixed')
  output = tmp_path / 'policy.npz'
  code, _, err = _main(
    capsys,
    f'--model={path}',
    '--algo=sac',
    '--domain=dkitty',
    '--task=stand_fixed',
    f'--output={output}',
  )
  assert code == 2
  assert err.count('\n') == 1 and 'dkitty/stand_fixed gives 61' in err
  assert not output.exists()


def test_bad_input_is_one_line(tmp_path, capsys):
  sac = _model(tmp_path, 'sac')
  output = f'--output={tmp_path / "policy.npz"}'
  task = ('--domain=dclaw', '--task=pose_fixed')
  cases = {
    'no model file': (f'--model={tmp_path / "none.zip"}', '--algo=sac'),
    '--algo must be one of sac, tqc, ppo': (f'--model={sac}', '--algo=td3'),
    'holds a SAC model, not TQC: give --algo=sac': (
      f'--model={sac}',
      '--algo=tqc',
    ),
  }
  for message, args in cases.items():
    code, _, err = _main(capsys, *args, *task, output)
    assert code == 2
    assert err.count('\n') == 1 and message in err, err
  not_zip = tmp_path / 'notes.zip'
  not_zip.write_text('not a model')
  code, _, err = _main(
    capsys, f'--model={not_zip}', '--algo=sac', *task, output
  )
  assert (code, err) == (2, f'error: {not_zip} is not a zip archive\n')
  assert not (tmp_path / 'policy.npz').exists()


@pytest.mark.slow
def test_actions_that_differ_are_refused(tmp_path, capsys, monkeypatch):
  path = _model(tmp_path, 'ppo')
  build = convert.agents.numpy_policy

  def off_by_a_little(model, metadata):
    policy = build(model, metadata)
    act = policy.act
    policy.act = lambda observations: act(observations) + 1e-3
    return policy

  monkeypatch.setattr(convert.agents, 'numpy_policy', off_by_a_little)
  output = tmp_path / 'policy.npz'
  code, _, err = _main(
    capsys,
    f'--model={path}',
    '--algo=ppo',
    '--domain=dclaw',
    '--task=pose_fixed',
    f'--output={output}',
  )
  assert code == 2
  assert err.startswith('error: the numpy policy differs from the model by')
  assert err.count('\n') == 1 and 'not converted' in err
  assert not output.exists()


@pytest.mark.slow
def test_evaluate_names_the_conversion_for_a_zip(tmp_path):
  path = _model(tmp_path, 'sac')
  with pytest.raises(ValueError, match='robel-convert') as error:
    evaluation.evaluate(
      evaluation.EvalConfig('dclaw', 'pose_fixed', 1, policy=str(path))
    )
  assert f'--model={path} --algo=ALGO --domain=dclaw' in str(error.value)
  result = subprocess.run(
    [
      sys.executable,
      '-m',
      'robel_dm.commands.evaluate',
      '--domain=dclaw',
      '--task=pose_fixed',
      f'--policy={path}',
    ],
    capture_output=True,
    text=True,
    timeout=120,
  )
  assert result.returncode == 2
  assert result.stderr.count('\n') == 1
  assert 'convert it to a policy.npz first' in result.stderr
