"""The bus diagnostics (`robel_dm.hardware.scan`) on the virtual servo bus.

Every scan goes through the unmodified dynamixel_sdk to a `PtyBusServer`
whose servos are set up for the test case.
"""

import contextlib
import io
import math
import subprocess
import sys

import pytest

from robel_dm.hardware import config as config_lib
from robel_dm.hardware import scan, virtual
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel.protocol import Instruction

# Without the hardware extra these tests are skipped, not errors.
sdk = pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
port_handler = sdk.port_handler

DCLAW = config_lib.default('dclaw')
DCLAW_IDS = virtual.robot_motor_ids(DCLAW)  # 9 joints, valve, guide.


@pytest.fixture(autouse=True)
def _short_sdk_timeouts(monkeypatch):
  # An absent motor then costs ~12 ms per ping instead of ~34 ms.
  monkeypatch.setattr(port_handler, 'LATENCY_TIMER', 5)


@contextlib.contextmanager
def _serve(ids=DCLAW_IDS, extra=()):
  """Serves servos `ids` (ROBEL's setup) plus the `extra` servos."""
  bus = virtual.Bus(virtual.make_servos(ids) + list(extra))
  with virtual.PtyBusServer(bus) as server:
    yield bus, server.device_path
  assert not server.errors


def _run(device, answers='', **kwargs):
  out, err = io.StringIO(), io.StringIO()
  kwargs.setdefault('robot_config', DCLAW)
  code = scan.run(
    device,
    scan.ScanOptions(**kwargs),
    answers=io.StringIO(answers),
    out=out,
    err=err,
  )
  return code, out.getvalue() + err.getvalue()


def _scan(device, all_ids=False):
  reports = scan.scan(device, scan.expected_ids(DCLAW), all_ids)
  return reports, scan.problems(reports, DCLAW, table.DEFAULT_BAUD_RATE)


def _kinds(problems):
  return {(problem.kind, problem.motor_id) for problem in problems}


def _main(*args):
  return subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.scan', *args],
    capture_output=True,
    text=True,
    timeout=60,
  )


def test_healthy_dclaw_bus_has_no_problems():
  with _serve() as (_, device):
    reports, problems = _scan(device)
    code, output = _run(device)
  assert [report.id for report in reports] == DCLAW_IDS
  assert problems == []
  report = reports[0]
  assert report.model_name == 'XH430-V350' and report.model_number == 1040
  assert report.firmware == virtual.DEFAULT_FIRMWARE
  assert report.position == 2048
  assert report.position_rad == pytest.approx(math.pi)
  assert report.temperature == virtual.DEFAULT_TEMPERATURE
  assert report.input_voltage == pytest.approx(24.0)
  assert report.operating_mode == table.POSITION_MODE
  assert report.baud_rate == 1_000_000
  assert report.return_delay_us == 0
  assert report.status_return_level == 2
  assert (report.min_position_limit, report.max_position_limit) == (0, 4095)
  assert report.torque_enabled is False
  assert report.hardware_error == 0 and report.hardware_error_names == []
  assert code == 0
  assert 'OK: 11 motor(s) found' in output
  assert '0 problem(s), 0 warning(s)' in output
  assert 'FFJ10' in output and 'XH430-V350 (1040)' in output


def test_the_table_gives_each_configured_joint_its_angle_through_the_offsets():
  # What calibrating an offset is checked against, with the torque off.
  config = config_lib.default('dclaw')
  first = config.joints[0]
  with _serve() as (bus, device):
    bus.servo(first.id).set_present(1024, 0, 0)
    code, output = _run(device, robot_config=config)
  assert code == 0
  joint = first.to_joint(1024 * table.RADIANS_PER_TICK)
  line = next(row for row in output.splitlines() if first.name in row)
  assert f'1024 (+1.571 rad; joint {joint:+.3f})' in line
  valve = next(m for m in config.auxiliary if m.id == 50)
  line = next(row for row in output.splitlines() if valve.name in row)
  assert f'joint {valve.to_joint(math.pi):+.3f}' in line


def test_firmware_refusing_block_reads_is_read_item_by_item(monkeypatch):
  with _serve() as (bus, device):
    bus.servo(11).set(table.OPERATING_MODE, 1)
    bus.servo(11).set_present(-5)
    blocks, _ = _scan(device)

    def refuse(self, motor_id, address, length):
      raise dynamixel.DynamixelError('access error', [motor_id])

    monkeypatch.setattr(dynamixel.DynamixelClient, 'read_bytes', refuse)
    items, _ = _scan(device)
  assert items == blocks
  assert items[1].operating_mode == 1 and items[1].position == -5


@pytest.mark.slow
def test_command_line_exits_0_on_a_healthy_bus():
  with _serve() as (_, device):
    result = _main(f'--device_path={device}', '--robot=dclaw')
  assert result.returncode == 0, result.stdout + result.stderr
  assert 'OK: 11 motor(s) found' in result.stdout


@pytest.mark.slow
def test_command_line_exits_2_for_a_missing_device():
  result = _main('--device_path=/dev/robel-dm-no-such-port', '--robot=dclaw')
  assert result.returncode == 2
  assert 'cannot open /dev/robel-dm-no-such-port' in result.stderr


@pytest.mark.slow
def test_command_line_exits_2_for_usage_errors():
  result = _main('--device_path=/dev/null', '--robot=dclaw', '--robot_config=x')
  assert result.returncode == 2
  assert 'not both' in result.stderr
  result = _main('--robot=dclaw')
  assert result.returncode == 2
  assert '--device_path is required' in result.stderr


def test_missing_motor_is_reported_by_id():
  with _serve([i for i in DCLAW_IDS if i != 22]) as (_, device):
    _, problems = _scan(device)
    code, output = _run(device)
  assert _kinds(problems) == {(scan.MISSING, 22)}
  assert code == 1
  assert 'motor 22 (MFJ22): expected but not found' in output


def test_missing_optional_and_task_specific_motors():
  with _serve(DCLAW.joint_ids) as (_, device):  # No valve (50), no guide (60).
    _, problems = _scan(device)
    code, _ = _run(device)
  (problem,) = problems
  assert (problem.kind, problem.motor_id) == (scan.MISSING, 50)
  assert problem.severity == scan.WARNING and 'turn, screw' in problem.message
  assert code == 0  # Warnings do not fail the scan.


@pytest.mark.slow
def test_no_motor_at_all_suggests_baud_and_all_ids():
  with _serve([]) as (_, device):
    code, output = _run(device)
  assert code == 1
  assert 'no motor answered at 1,000,000 bps' in output
  assert '--all_ids' in output


@pytest.mark.slow
def test_wrong_baud_without_expectations_fails_naming_what_was_tried():
  # Nothing expected: every ID is pinged, and finding none is no success.
  with _serve() as (_, device):
    code, output = _run(device, robot_config=None, baud_rate=57_600)
    # --device: the flag's first name, still taken.
    result = _main(f'--device={device}', '--baud=57600')
  assert code == 1, output
  assert 'PROBLEMS: 0 motor(s) found' in output
  assert 'no motor answered at 57,600 bps (tried every ID 0-252)' in output
  assert '--baud=RATE, one of 9600, 115200, 1000000,' in output
  assert result.returncode == 1, result.stdout + result.stderr
  assert 'tried every ID 0-252' in result.stdout


@pytest.mark.slow
def test_wrong_baud_with_a_configuration_names_the_ids_tried():
  with _serve() as (_, device):
    code, output = _run(device, baud_rate=57_600)
  assert code == 1
  assert 'tried ID(s) 10-12, 20-22, 30-32, 50, 60' in output
  assert '--all_ids' in output
  assert '(57600: new motors)' not in output  # It was the rate tried.


@pytest.mark.slow
def test_empty_bus_at_robel_rate_points_to_the_factory_rate():
  with _serve([]) as (_, device):
    code, output = _run(device, robot_config=None)
  assert code == 1
  assert 'one of 9600, 57600, 115200, 2000000' in output
  assert '(57600: new motors)' in output


@pytest.mark.slow
def test_wrong_operating_mode_is_flagged():
  with _serve() as (bus, device):
    bus.servo(11).set(table.OPERATING_MODE, 1)
    reports, problems = _scan(device)
    code, output = _run(device)
  assert reports[1].operating_mode == 1
  assert _kinds(problems) == {(scan.OPERATING_MODE, 11)}
  assert code == 1
  assert 'motor 11 (FFJ11): operating mode 1 (velocity)' in output


def test_return_delay_is_flagged_with_its_cost():
  with _serve() as (bus, device):
    bus.servo(12).set(table.RETURN_DELAY_TIME, 250)
    _, problems = _scan(device)
  (problem,) = problems
  assert (problem.kind, problem.motor_id) == (scan.RETURN_DELAY, 12)
  assert '500 us' in problem.message


def test_status_return_level_is_flagged():
  with _serve() as (bus, device):
    bus.servo(20).set(table.STATUS_RETURN_LEVEL, 1)
    bus.servo(21).set(table.STATUS_RETURN_LEVEL, 0)  # Answers pings only.
    _, problems = _scan(device)
  assert _kinds(problems) == {
    (scan.STATUS_RETURN_LEVEL, 20),
    (scan.UNREADABLE, 21),
  }


@pytest.mark.slow
def test_extra_unknown_motor_is_reported():
  unknown = virtual.VirtualServo(99, model_number=1200)
  with _serve(extra=[unknown]) as (_, device):
    reports, problems = _scan(device, all_ids=True)
    code, output = _run(device, all_ids=True)
    not_scanned, _ = _scan(device)  # Without --all_ids only expected IDs.
  assert [report.id for report in reports] == DCLAW_IDS + [99]
  assert _kinds(problems) == {(scan.EXTRA, 99), (scan.UNKNOWN_MODEL, 99)}
  assert code == 1
  assert 'motor 99: on the bus but not in the configuration' in output
  assert 'unknown model number 1200' in output
  assert 99 not in [report.id for report in not_scanned]


@pytest.mark.slow
def test_expected_ids_without_a_configuration():
  with _serve([1, 2, 7]) as (_, device):
    code, output = _run(device, robot_config=None, ids=[1, 2, 3], all_ids=True)
  assert code == 1
  assert 'motor 3: expected but not found' in output
  assert 'motor 7: on the bus but not in --ids' in output


def test_hardware_error_is_reported_with_its_name():
  with _serve() as (bus, device):
    bus.servo(21).set(table.TORQUE_ENABLE, 1)
    bus.servo(21).inject_hardware_error(0x20)  # Overload: torque cut.
    reports, problems = _scan(device)
    code, output = _run(device)
  (report,) = [report for report in reports if report.id == 21]
  assert report.hardware_error_names == ['overload']
  assert report.torque_enabled is False
  (problem,) = problems
  assert (problem.kind, problem.motor_id) == (scan.HARDWARE_ERROR, 21)
  assert 'overload' in problem.message and 'reboot' in problem.message
  assert code == 1


def test_apply_yes_fixes_mode_and_return_delay():
  with _serve() as (bus, device):
    servo = bus.servo(11)
    servo.set(table.OPERATING_MODE, 1)
    servo.set(table.RETURN_DELAY_TIME, 250)
    servo.set(table.TORQUE_ENABLE, 1)
    bus.servo(22).set(table.STATUS_RETURN_LEVEL, 0)
    code, output = _run(device, apply=True, yes=True)
    _, problems = _scan(device)
    assert servo.operating_mode == table.POSITION_MODE
    assert servo.get(table.RETURN_DELAY_TIME) == 0
    assert not servo.torque_enabled
    assert bus.servo(22).status_return_level == 2
  assert code == 0, output
  assert problems == []
  assert 'Operating Mode (address 11): 1 (velocity) -> 3 (position)' in output
  assert 'Return Delay Time (address 9): 250 (500 us) -> 0 (0 us)' in output
  assert 'motor 11 (FFJ11): turning torque off' in output
  assert 'motor 11 (FFJ11): written and read back' in output
  assert 'After --apply' in output


def test_apply_answer_n_leaves_the_motor_unchanged():
  with _serve() as (bus, device):
    bus.servo(11).set(table.OPERATING_MODE, 1)
    bus.servo(12).set(table.RETURN_DELAY_TIME, 250)
    bus.servo(12).set(table.TORQUE_ENABLE, 1)
    writes_before = bus.servo(12).counters[Instruction.WRITE]
    code, output = _run(device, answers='y\nn\n', apply=True)
    assert bus.servo(11).operating_mode == table.POSITION_MODE
    assert bus.servo(12).get(table.RETURN_DELAY_TIME) == 250
    assert bus.servo(12).torque_enabled
    assert bus.servo(12).counters[Instruction.WRITE] == (writes_before)
  assert code == 1
  assert 'Write these to motor 12 (FFJ12)? [y/N]' in output
  assert 'motor 12 (FFJ12): left unchanged' in output


def test_apply_without_answers_writes_nothing():
  with _serve() as (bus, device):
    bus.servo(11).set(table.OPERATING_MODE, 1)
    code, _ = _run(device, answers='', apply=True)  # stdin at its end.
    assert bus.servo(11).operating_mode == 1
  assert code == 1


@pytest.mark.slow
def test_apply_leaves_motors_that_are_not_expected_alone():
  stranger = virtual.VirtualServo(99)
  stranger.set(table.OPERATING_MODE, 1)  # E.g. a wheel, on purpose.
  with _serve(extra=[stranger]) as (_, device):
    code, output = _run(device, all_ids=True, apply=True, yes=True)
    assert stranger.operating_mode == 1
  assert code == 1
  assert 'motor 99: not expected here, not touched' in output


def test_position_limits_are_a_warning_unless_they_cut_configured_limits():
  report = scan.MotorReport(
    10, 1040, firmware=46, position=2048, temperature=35,
    input_voltage_raw=120, operating_mode=3, baud_register=3,
    return_delay_time=0, status_return_level=2, min_position_limit=1024,
    max_position_limit=3072, torque_enable=0, hardware_error=0,
  )  # fmt: skip
  (problem,) = scan.problems([report], None)
  assert problem.kind == scan.POSITION_LIMITS
  assert problem.severity == scan.WARNING
  # FFJ10: joint = motor angle - pi / 2, so 1024..3072 ticks is 0..pi rad.
  (problem,) = [p for p in scan.problems([report], DCLAW) if p.motor_id == 10]
  assert 'kept within [0.000, 3.142] rad' in problem.message
  narrow = config_lib.from_dict(
    {
      'robot': 'dclaw',
      'joints': [{'name': 'FFJ10', 'id': 10, 'offset_pi': -0.5}],
      'limits': {'FFJ10': [-0.5, 0.5]},
    }
  )
  (problem,) = scan.problems([report], narrow)
  assert problem.severity == scan.ERROR
  assert 'does not cover its configured limits' in problem.message


def test_baud_rate_mismatches():
  report = scan.MotorReport(
    10, 1040, firmware=46, position=2048, temperature=35,
    input_voltage_raw=120, operating_mode=3, baud_register=1,
    return_delay_time=0, status_return_level=2, min_position_limit=0,
    max_position_limit=4095, torque_enable=0, hardware_error=0,
  )  # fmt: skip
  assert scan.problems([report], None, baud_rate=57_600) == []
  (problem,) = scan.problems([report], None)
  assert (problem.kind, problem.motor_id) == (scan.BAUD_RATE, 10)
  assert '57,600 bps' in problem.message
  kinds = _kinds(scan.problems([report], DCLAW, baud_rate=57_600))
  assert (scan.BAUD_RATE, None) in kinds  # The configuration uses 1 Mbps.


def test_parse_ids_and_configurations():
  assert scan.parse_ids('10, 11,20-22') == [10, 11, 20, 21, 22]
  assert scan.parse_ids(None) == []
  for bad in ('x', '10-', '253', '5-300'):
    with pytest.raises(scan.UsageError, match='--ids'):
      scan.parse_ids(bad)
  assert scan.load_config('dkitty', None).robot == 'dkitty'
  assert scan.load_config(None, None) is None
  with pytest.raises(scan.UsageError, match='not found'):
    scan.load_config(None, '/no/such/robot.json')
