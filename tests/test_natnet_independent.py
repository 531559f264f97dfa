"""The NatNet layout checked against an independent decoder.

The `natnet` package on PyPI (a maintained NatNet client, used here as a
test-only reference) decodes every frame robel_dm's encoder writes, in every
supported version: the rigid bodies' IDs, positions, orientations and the
tracking-valid bit agree with robel_dm's own decoder. Version detection
tells the 4.1 layout (sections with byte counts) from 3.x/4.0.
"""

import numpy as np
import pytest

from robel_dm.hardware.tracking import natnet

reference = pytest.importorskip(
  'natnet.data_frame', reason='needs robel_dm[dev]'
)
from natnet.packet_buffer import PacketBuffer  # noqa: E402
from natnet.version import Version  # noqa: E402

_BODIES = [
  natnet.RigidBody(1, (0.1, -0.2, 0.3), (0.9, 0.1, -0.3, 0.3)),
  natnet.RigidBody(7, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)),
  natnet.RigidBody(12, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0.5, False),
]


@pytest.mark.parametrize('version', natnet.SUPPORTED_VERSIONS)
def test_an_independent_decoder_reads_the_same_frames(version):
  datagram = natnet.encode_frame(
    42,
    _BODIES,
    marker_sets={'torso': [(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)]},
    unlabeled_markers=[(7.0, 8.0, 9.0)],
    version=version,
  )
  theirs = reference.DataFrame.read_from_buffer(
    PacketBuffer(datagram[4:]), Version(*version)
  )
  ours = natnet.decode_message(datagram, version)
  assert theirs.prefix.frame_number == ours.frame_number == 42
  assert [s.model_name for s in theirs.marker_sets] == ['torso']
  assert len(theirs.unlabeled_marker_pos) == 1
  assert len(theirs.rigid_bodies) == len(ours.rigid_bodies) == 3
  for their, our in zip(theirs.rigid_bodies, ours.rigid_bodies, strict=True):
    assert their.id_num == our.id
    np.testing.assert_allclose(their.pos, our.position, atol=1e-6)
    qx, qy, qz, qw = their.rot  # NatNet sends x, y, z, w.
    np.testing.assert_allclose((qw, qx, qy, qz), our.quaternion, atol=1e-6)
    assert their.tracking_valid == our.tracking_valid


@pytest.mark.parametrize('version', natnet.SUPPORTED_VERSIONS)
def test_the_layout_is_detected_from_a_frame(version):
  for bodies in ([], _BODIES):
    datagram = natnet.encode_frame(
      3, bodies, marker_sets={'a': [(1.0, 1.0, 1.0)]}, version=version
    )
    expected = (4, 1) if version == (4, 1) else (4, 0)
    assert natnet.detect_version(datagram[4:]) == expected


def test_the_client_detects_the_version_of_the_stream():
  import socket  # noqa: PLC0415
  import time  # noqa: PLC0415

  with (
    natnet.NatNetClient(
      multicast_group=None, data_port=0, local_interface='127.0.0.1'
    ) as client,
    socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender,
  ):
    assert client.version is None
    sender.sendto(
      natnet.encode_frame(1, _BODIES[:1], version=(4, 1)), client.address
    )
    deadline = time.monotonic() + 2
    poses = {}
    while not poses and time.monotonic() < deadline:
      poses = client.poll()
      time.sleep(0.01)
    assert client.version == (4, 1)
    np.testing.assert_allclose(poses['1'].position, (0.1, -0.2, 0.3))
