"""--tracker names a NatNet stream; a D'Kitty evaluation runs on it."""

import socket
import threading
import time

import numpy as np
import pytest

from robel_dm import evaluation, suite
from robel_dm.hardware.tracking import natnet
from robel_dm.hardware.tracking import spec as tracker_spec

# The virtual bus.
pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')


def test_specs_parse_with_defaults_and_reject_mistakes():
  fields = tracker_spec.parse('natnet:10.0.0.5,rigid_body=1,target=2')
  assert fields['server'] == '10.0.0.5'
  assert fields['command_port'] == natnet.DEFAULT_COMMAND_PORT
  assert fields['data_port'] == natnet.DEFAULT_DATA_PORT
  assert 'version' not in fields and fields['y_up'] is True
  assert tracker_spec.parse('natnet:h:1600,rigid_body=3,version=3.1,'
                            'y_up=false')['version'] == (3, 1)  # fmt: skip
  for bad, message in [
    ('vicon:h,rigid_body=1', 'expected natnet'),
    ('natnet:h', 'rigid_body'),
    ('natnet:h,rigid_body=1,colour=red', 'unknown option'),
    ('natnet:h:x,rigid_body=1', 'bad port'),
    ('natnet:h,rigid_body=1,y_up=maybe', 'y_up'),
  ]:
    with pytest.raises(tracker_spec.TrackerSpecError, match=message):
      tracker_spec.parse(bad)


def _free_port() -> int:
  with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
    probe.bind(('127.0.0.1', 0))
    return probe.getsockname()[1]


@pytest.mark.slow
def test_the_tracker_flag_reaches_a_natnet_stream_over_loopback():
  data_port = _free_port()
  # Motive's side: a command socket, and frames of a standing torso
  # (z-up stream: y_up=false) sent to the client's data port.
  server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
  server.bind(('127.0.0.1', 0))
  command_port = server.getsockname()[1]
  stop = threading.Event()
  sent = [0]

  def stream():
    torso = natnet.RigidBody(1, (0.0, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0))
    while not stop.is_set():
      frame = natnet.encode_frame(sent[0], [torso], version=(4, 0))
      server.sendto(frame, ('127.0.0.1', data_port))
      sent[0] += 1
      time.sleep(0.005)

  sender = threading.Thread(target=stream, daemon=True)
  sender.start()
  try:
    results = evaluation.evaluate(evaluation.EvalConfig(
      'dkitty', 'stand_fixed', 1, policy='zero',
      robot=suite.RobotOptions('virtual', tracker=(
        f'natnet:127.0.0.1:{command_port},rigid_body=1,multicast=unicast,'
        f'data_port={data_port},local=127.0.0.1,y_up=false')),
    ))  # fmt: skip
  finally:
    stop.set()
    sender.join(5)
  # The unicast client subscribed at Motive's command port.
  server.settimeout(1)
  request, _ = server.recvfrom(1024)
  assert request[:2] == bytes([natnet.NAT_CONNECT, 0])
  server.close()
  assert results['episodes'] == 1 and sent[0] > 10
  # The tracked torso never moved: the robot counted as standing still.
  assert np.isfinite(results['mean_return'])


def test_a_tracker_on_a_robot_without_a_free_torso_is_refused_unopened():
  # A tracker spec that nothing listens on: refused before it is opened.
  with pytest.raises(ValueError, match='has no free torso: a tracker'):
    suite.load(
      'dclaw',
      'pose_fixed',
      robot=suite.RobotOptions(
        'virtual', tracker='natnet:127.0.0.1,rigid_body=1'
      ),
    )
