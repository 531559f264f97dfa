"""The tracker layer's NatNet client: frames of every supported version,
rigid bodies over loopback UDP (multicast and unicast), and a torso tracker
that says what it misses.

Network traffic stays on 127.0.0.0/8; every wait is bounded.
"""

import socket
import time

import numpy as np
import pytest

from robel_dm import geometry as geo
from robel_dm.hardware.tracking import natnet
from robel_dm.hardware.tracking import tracker as tr

_WAIT = 2.0  # s, the longest any test waits for a datagram.


# --- NatNet -------------------------------------------------------------------


def _bodies():
  return [
    natnet.RigidBody(1, (0.1, 1.2, -0.3), (0.9, 0.1, -0.3, 0.3), 0.0004),
    # w < 0: the other hemisphere, decoded as sent.
    natnet.RigidBody(7, (-2.0, 0.5, 4.0), (-0.5, 0.5, 0.5, -0.5), 0.001),
    natnet.RigidBody(12, (3.0, 3.0, 3.0), (1.0, 0.0, 0.0, 0.0), 0.0, False),
  ]


def _marker_sets():
  return {
    'kitty': [(0.1, 0.2, 0.3), (0.4, 0.5, 0.6), (0.7, 0.8, 0.9)],
    'all': [(1.0, 2.0, 3.0)],
  }


@pytest.mark.parametrize('version', natnet.SUPPORTED_VERSIONS)
def test_natnet_frames_round_trip(version):
  datagram = natnet.encode_frame(
    41,
    _bodies(),
    marker_sets=_marker_sets(),
    unlabeled_markers=[(5.0, 6.0, 7.0), (8.0, 9.0, 10.0)],
    version=version,
  )
  frame = natnet.decode_message(datagram, version)
  assert frame.frame_number == 41
  assert [b.id for b in frame.rigid_bodies] == [1, 7, 12]
  for sent, got in zip(_bodies(), frame.rigid_bodies, strict=True):
    # float32 on the wire.
    assert np.allclose(got.position, sent.position, atol=1e-6)
    assert np.allclose(got.quaternion, sent.quaternion, atol=1e-7)
    assert got.mean_error == pytest.approx(sent.mean_error, rel=1e-6)
    assert got.tracking_valid == sent.tracking_valid
  # Truncation anywhere up to the last rigid body's end is detected. After
  # it come the encoder's empty sections (4 in 3.x/4.0, 5 with 4.1's byte
  # counts) and 46 bytes of timing fields, which the decoder does not read.
  sized = version >= (4, 1)
  tail = (5 * 8 if sized else 4 * 4) + 46
  rigid_end = len(datagram) - tail
  payload = datagram[4:rigid_end]
  assert natnet.decode_frame(payload, version) == frame
  for cut in (2, 20, len(payload) - 1):
    with pytest.raises(natnet.NatNetError, match='truncated'):
      natnet.decode_frame(payload[:cut], version)
  for cut in (3, 20):  # The header's payload size catches short datagrams.
    with pytest.raises(natnet.NatNetError):
      natnet.decode_message(datagram[:cut], version)
  assert natnet.decode_message(natnet.encode_request(10), version) is None


def test_natnet_versions_and_layouts():
  with pytest.raises(ValueError, match='not supported'):
    natnet.decode_frame(b'', (2, 9))
  with pytest.raises(ValueError, match='not supported'):
    natnet.NatNetClient(multicast_group=None, data_port=0, version=(5, 0))
  # 4.1 prefixes each section with its byte count; the layouts differ.
  bodies = _bodies()[:1]
  assert len(natnet.encode_frame(0, bodies, version=(4, 1))) > len(
    natnet.encode_frame(0, bodies, version=(4, 0))
  )
  assert natnet.encode_frame(0, bodies, version=(3, 0)) == natnet.encode_frame(
    0, bodies, version=(4, 0)
  )


def _wait_for(poll, count=1):
  """Polls until `count` bodies arrived in total (bounded by _WAIT)."""
  received = {}
  deadline = time.monotonic() + _WAIT
  while len(received) < count and time.monotonic() < deadline:
    received.update(poll())
    time.sleep(0.002)
  return received


@pytest.mark.parametrize('version', [(3, 1), (4, 0), (4, 1)])
def test_natnet_client_receives_rigid_bodies_over_loopback(version):
  with (
    natnet.NatNetClient(
      multicast_group=None,
      data_port=0,
      local_interface='127.0.0.1',
      version=version,
    ) as client,
    socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender,
  ):
    sender.sendto(b'\x07\x00', client.address)  # Malformed: counted.
    datagram = natnet.encode_frame(
      1,
      _bodies(),
      marker_sets=_marker_sets(),
      unlabeled_markers=[(5.0, 6.0, 7.0)],
      version=version,
    )
    sent_at = time.monotonic()
    sender.sendto(datagram, client.address)
    poses = _wait_for(client.poll, 2)
    # Body 12 is not tracked in this frame: dropped.
    assert sorted(poses) == ['1', '7']
    for body in _bodies()[:2]:
      pose = poses[str(body.id)]
      assert np.allclose(pose.position, body.position, atol=1e-6)
      assert np.allclose(pose.quaternion, body.quaternion, atol=1e-7)
      assert sent_at <= pose.timestamp <= time.monotonic()
    assert client.poll() == {}  # Nothing new.
    # A later frame updating body 7 only.
    moved = natnet.RigidBody(7, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    datagram = natnet.encode_frame(2, [moved], version=version)
    sender.sendto(datagram, client.address)
    poses = _wait_for(client.poll)
    assert list(poses) == ['7']
    assert np.allclose(poses['7'].position, (0, 0, 1))
    assert set(client.latest()) == {'1', '7'}
    stats = client.stats
    assert stats['frames'] == 2 and stats['malformed'] == 1
    assert stats['invalid'] == 1
    assert 'malformed' in client.status()
  assert 'NatNet' in client.status()  # Still describes itself once closed.


def test_natnet_unicast_subscribes_and_ignores_other_hosts():
  with (
    socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as server,
    socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger,
  ):
    server.bind(('127.0.0.1', 0))  # Motive's command port.
    server.settimeout(_WAIT)
    stranger.bind(('127.0.0.2', 0))
    with natnet.NatNetClient(
      multicast_group=None,
      data_port=0,
      local_interface='127.0.0.1',
      server_address='127.0.0.1',
      command_port=server.getsockname()[1],
    ) as client:
      request, client_address = server.recvfrom(1024)
      assert request[:2] == bytes([natnet.NAT_CONNECT, 0])
      assert client_address == client.address
      body = natnet.RigidBody(3, (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))
      stray = natnet.RigidBody(4, (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))
      stranger.sendto(natnet.encode_frame(1, [stray]), client_address)
      server.sendto(natnet.encode_frame(1, [body]), client_address)
      assert list(_wait_for(client.poll)) == ['3']
      time.sleep(0.05)
      assert client.poll() == {}  # The stranger's frame was ignored.


def test_torso_tracker_on_natnet_reports_what_is_missing():
  with natnet.NatNetClient(
    multicast_group=None, data_port=0, local_interface='127.0.0.1'
  ) as client:
    tracker = tr.TorsoTracker(client, body=5, frames=tr.Frames(tr.Y_UP_TO_Z_UP))
    with pytest.raises(tr.TrackingError, match=r"torso body '5'.*0 frames"):
      tracker.torso_state()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
      # Motive's default frame is y-up: a level torso has its z-axis along
      # the tracker's +y.
      level = geo.matrix_to_quat(tr.Y_UP_TO_Z_UP.T)
      body = natnet.RigidBody(5, (0.0, 0.4, 0.0), tuple(level))
      sender.sendto(natnet.encode_frame(1, [body]), client.address)
      deadline = time.monotonic() + _WAIT
      while not tracker.update() and time.monotonic() < deadline:
        time.sleep(0.002)
    position, quaternion, _, _ = tracker.torso_state()
    assert np.allclose(position, (0, 0, 0.4), atol=1e-6)
    assert geo.quat_to_matrix(quaternion)[2, 2] == pytest.approx(1.0)
