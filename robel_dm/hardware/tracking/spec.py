"""Motion trackers named on the command line.

    --tracker=natnet:SERVER[:COMMAND_PORT],rigid_body=ID[,option=value,...]

`SERVER` is Motive's IPv4 address or host name. Options:
  rigid_body  the torso's rigid-body streaming ID (required);
  target      the Orient/Walk target's rigid body;
  heading     the Walk heading marker's rigid body (the target's otherwise);
  multicast   the multicast group Motive streams to, or 'unicast'
              (default: Motive's 239.255.42.99);
  data_port   the local port frames arrive on (default 1511; 0, any free
              port, with unicast only);
  local       the local IPv4 address to bind / join on (default 0.0.0.0);
  version     Motive's NatNet bitstream version, e.g. 4.1 (default:
              detected from the first frame);
  y_up        whether Motive streams y-up (its default): true or false.

Every field is checked when the spec is parsed, before any socket opens: a
mistake raises `TrackerSpecError` with one line naming the field and value.
"""

import ipaddress
import re
import socket

from robel_dm.hardware.tracking import natnet
from robel_dm.hardware.tracking import tracker as tracking

_SCHEME = 'natnet:'
_OPTIONS = (
  'rigid_body',
  'target',
  'heading',
  'multicast',
  'data_port',
  'local',
  'version',
  'y_up',
)
_BODIES = ('rigid_body', 'target', 'heading')
_MAX_PORT = 65535
_MAX_BODY_ID = 2**31 - 1  # NatNet IDs are 32-bit signed integers.
_DIGITS = re.compile(r'[0-9]+')
_HOST_LABEL = re.compile(r'[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?')


class TrackerSpecError(ValueError):
  """A --tracker value that cannot be understood."""


def _integer(field: str, value: str, low: int, high: int, what: str) -> int:
  if not _DIGITS.fullmatch(value) or not low <= int(value) <= high:
    raise TrackerSpecError(f'--tracker: {field} {value!r} is not {what}')
  return int(value)


def _ipv4(field: str, value: str) -> ipaddress.IPv4Address:
  try:
    return ipaddress.IPv4Address(value)
  except ValueError:
    raise TrackerSpecError(
      f'--tracker: {field} {value!r} is not an IPv4 address'
    ) from None


def _check_server(server: str) -> None:
  """Motive's address: an IPv4 address, or a host name (resolved by
  `make_tracker`)."""
  labels = server.split('.')
  if _DIGITS.fullmatch(labels[-1]):  # Numeric: an address, not a name.
    address = _ipv4('server', server)
    if address.is_multicast or address.is_unspecified:
      raise TrackerSpecError(
        f'--tracker: server {server!r} is not a host address'
      )
    return
  if len(server) > 253 or not all(map(_HOST_LABEL.fullmatch, labels)):
    raise TrackerSpecError(
      f'--tracker: server {server!r} is neither an IPv4 address nor a host name'
    )


def _check_multicast(value: str) -> None:
  if value == 'unicast':
    return
  if not _ipv4('multicast', value).is_multicast:
    raise TrackerSpecError(
      f'--tracker: multicast {value!r} is not a multicast group '
      "(224.0.0.0..239.255.255.255) or 'unicast'"
    )


def _version(value: str) -> tuple[int, int]:
  major, _, minor = value.partition('.')
  if _DIGITS.fullmatch(major) and (not minor or _DIGITS.fullmatch(minor)):
    version = (int(major), int(minor or 0))
    if version in natnet.SUPPORTED_VERSIONS:
      return version
  supported = ', '.join(f'{a}.{b}' for a, b in natnet.SUPPORTED_VERSIONS)
  raise TrackerSpecError(
    f'--tracker: version {value!r} is not a supported NatNet version '
    f'({supported})'
  )


def parse(spec: str) -> dict:
  """The fields of a tracker spec (see the module docstring), each checked.

  Raises:
    TrackerSpecError: naming the field and value that are wrong.
  """
  if not spec.startswith(_SCHEME):
    raise TrackerSpecError(
      f'--tracker {spec!r}: expected natnet:SERVER[:PORT],rigid_body=ID,...'
    )
  address, *pairs = spec[len(_SCHEME) :].split(',')
  fields = _parse_address(spec, address)
  options = _parse_options(pairs)
  fields.update(_parse_bodies(options))
  fields.update(_parse_network(options))
  fields.update(_parse_stream(options))
  return fields


def _parse_address(spec: str, address: str) -> dict:
  """`server` and `command_port` from SERVER[:COMMAND_PORT]."""
  server, colon, port = address.partition(':')
  if not server:
    raise TrackerSpecError(f'--tracker {spec!r}: no server address')
  _check_server(server)
  fields = {'server': server, 'command_port': natnet.DEFAULT_COMMAND_PORT}
  if colon:
    if not _DIGITS.fullmatch(port) or not 1 <= int(port) <= _MAX_PORT:
      raise TrackerSpecError(
        f'--tracker: bad port {port!r}: the command port is 1..{_MAX_PORT}'
      )
    fields['command_port'] = int(port)
  return fields


def _parse_options(pairs: list[str]) -> dict[str, str]:
  """The option=value pairs as a dict: known options, each given once."""
  options = {}
  for pair in pairs:
    key, sep, value = pair.partition('=')
    key = key.strip()
    if key in _OPTIONS and not sep:
      raise TrackerSpecError(f'--tracker: option {key} needs a value')
    if key not in _OPTIONS:
      raise TrackerSpecError(
        f'--tracker: unknown option {pair!r}; options are {list(_OPTIONS)}'
      )
    if key in options:
      raise TrackerSpecError(f'--tracker: {key} is given twice')
    options[key] = value.strip()
  return options


def _parse_bodies(options: dict[str, str]) -> dict:
  """The rigid-body IDs (`rigid_body` required, `target`, `heading`)."""
  if 'rigid_body' not in options:
    raise TrackerSpecError('--tracker: rigid_body=ID (the torso) is required')
  bodies = {}
  for key in _BODIES:
    if key in options:
      bodies[key] = _integer(
        key, options[key], 1, _MAX_BODY_ID,
        f'a rigid-body ID (1..{_MAX_BODY_ID})',
      )  # fmt: skip
  return bodies


def _parse_network(options: dict[str, str]) -> dict:
  """Where frames arrive: `multicast`, `data_port` (always) and `local`."""
  fields = {}
  if 'multicast' in options:
    _check_multicast(options['multicast'])
    fields['multicast'] = options['multicast']
  unicast = options.get('multicast') == 'unicast'
  fields['data_port'] = natnet.DEFAULT_DATA_PORT
  if 'data_port' in options:
    low = 0 if unicast else 1  # 0 (any free port) serves unicast only.
    fields['data_port'] = _integer(
      'data_port', options['data_port'], low, _MAX_PORT,
      f'a port number ({low}..{_MAX_PORT})',
    )  # fmt: skip
  if 'local' in options:
    if _ipv4('local', options['local']).is_multicast:
      raise TrackerSpecError(
        f'--tracker: local {options["local"]!r} is a multicast group, not '
        'an address of this machine'
      )
    fields['local'] = options['local']
  return fields


def _parse_stream(options: dict[str, str]) -> dict:
  """What the frames hold: `version` (if given) and `y_up` (always)."""
  fields = {}
  if 'version' in options:
    fields['version'] = _version(options['version'])
  y_up = options.get('y_up', 'true')
  if y_up.lower() not in ('true', 'false'):
    raise TrackerSpecError(f'--tracker: y_up {y_up!r} is not true or false')
  fields['y_up'] = y_up.lower() == 'true'
  return fields


def _resolve(server: str) -> str:
  """The IPv4 address of Motive's host (NatNet frames are matched by their
  sender's address)."""
  try:
    return socket.gethostbyname(server)
  except OSError as error:
    raise TrackerSpecError(
      f'--tracker: server {server!r} cannot be resolved: '
      f'{error.strerror or error}'
    ) from None


def make_tracker(spec: str) -> tracking.TorsoTracker:
  """A `TorsoTracker` on the NatNet stream a spec names.

  Raises:
    TrackerSpecError: for a malformed spec, a server name that does not
      resolve, or a socket that cannot be opened (e.g. `local` is not an
      address of this machine, or `data_port` is in use).
  """
  fields = parse(spec)
  multicast = fields.get('multicast', natnet.DEFAULT_MULTICAST_GROUP)
  unicast = multicast == 'unicast'
  local = fields.get('local', '0.0.0.0')
  try:
    client = natnet.NatNetClient(
      multicast_group=None if unicast else multicast,
      data_port=fields['data_port'],
      local_interface=local,
      server_address=_resolve(fields['server']),
      command_port=fields['command_port'],
      version=fields.get('version'),
    )
  except OSError as error:
    raise TrackerSpecError(
      f'--tracker: cannot open the NatNet socket (local={local}, '
      f'data_port={fields["data_port"]}, multicast={multicast}): '
      f'{error.strerror or error}'
    ) from None
  return tracking.TorsoTracker(
    client,
    fields['rigid_body'],
    target_body=fields.get('target'),
    heading_body=fields.get('heading'),
    frames=tracking.Frames(tracking.Y_UP_TO_Z_UP) if fields['y_up'] else None,
  )
