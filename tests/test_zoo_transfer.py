"""The transfer table: shipped policies on the zoo's robots."""

import shutil

import pytest

# The robots run on the virtual bus.
pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')

from robel_dm import assets, policies, zoo  # noqa: E402
from robel_dm.zoo import transfer  # noqa: E402


def test_randomdynamics_policies_run_on_the_random_task():
  assert transfer.evaluated_task('pose_random_dynamics') == 'pose_random'
  assert transfer.evaluated_task('walk_fixed') == 'walk_fixed'


@pytest.mark.slow
def test_a_transfer_record_is_made_merged_and_tabled(tmp_path, monkeypatch):
  monkeypatch.setitem(transfer.EPISODES, 'fixed', 1)
  configs, evaluate = [], transfer.evaluation.evaluate

  def spy(config, **kwargs):
    configs.append(config)
    return evaluate(config, **kwargs)

  monkeypatch.setattr(transfer.evaluation, 'evaluate', spy)
  (pairing,) = transfer.pairings('dclaw_pose_fixed/claw_noisy')
  record = transfer.evaluate_pairing(pairing)
  # On the zoo robot, over the virtual bus.
  (config,) = configs
  assert config.robot.device_path == 'virtual'
  assert config.dynamics == str(zoo.robot('claw_noisy').path)
  assert record['robot'] == 'claw_noisy'
  assert record['task'] == 'dclaw/pose_fixed'
  assert record['episodes'] == 1
  assert set(record['violations']) == {'position', 'velocity', 'current'}
  results = tmp_path / 'transfer.json'
  transfer.merge([record], results)
  transfer.merge([dict(record, success=0.5)], results)  # Replaces it.
  (kept,) = transfer.load_records(results)
  assert kept['success'] == 0.5
  doc = tmp_path / transfer.DOC.name
  shutil.copy(transfer.DOC, doc)
  transfer.report([kept], doc)
  table = doc.read_text()
  # The tables are made anew from the one record.
  assert transfer.domain_table([kept], 'dclaw') in table
  assert transfer.domain_table(transfer.load_records(), 'dclaw') not in table
  assert transfer.robots_table() in table


def test_the_docs_tables_are_made_from_the_records():
  records = transfer.load_records()
  text = transfer.DOC.read_text()
  assert transfer.robots_table() in text
  for domain in ('dclaw', 'dkitty'):
    assert transfer.domain_table(records, domain) in text


def test_the_records_are_of_the_policies_shipped_now():
  """A shipped policy replaced by the baseline report makes its records
  stale: every record names the agent and seed of the policy in
  `policies/` (and every shipped policy has records)."""
  records = transfer.load_records()
  shipped = {path.stem: path for path in assets.baselines_dir().glob('*.npz')}
  assert {record['policy'] for record in records} == set(shipped)
  for record in records:
    metadata = policies.load(shipped[record['policy']]).metadata
    assert (record['agent'], record['training_seed']) == (
      metadata['algo'],
      metadata['seed'],
    ), record['policy']


def test_a_pattern_that_matches_no_pairing_is_an_error(capsys):
  from robel_dm.commands import zoo as zoo_cli  # noqa: PLC0415

  assert zoo_cli.main(['evaluate', '--only=pose_*/*']) == 2
  assert "matches no 'policy/robot' pairing" in capsys.readouterr().err
