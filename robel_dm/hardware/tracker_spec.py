"""Motion trackers named on the command line.

    --tracker=natnet:SERVER[:COMMAND_PORT],rigid_body=ID[,option=value,...]

`SERVER` is Motive's address. Options:
  rigid_body  the torso's rigid-body streaming ID (required);
  target      the Orient/Walk target's rigid body;
  heading     the Walk heading marker's rigid body (the target's otherwise);
  multicast   the multicast group Motive streams to, or 'unicast'
              (default: Motive's 239.255.42.99);
  data_port   the local port frames arrive on (default 1511);
  local       the local address to bind / join on (default 0.0.0.0);
  version     Motive's NatNet bitstream version, e.g. 4.1 (default:
              detected from the first frame);
  y_up        whether Motive streams y-up (its default): true or false.
"""

from robel_dm.hardware import natnet, tracking

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


class TrackerSpecError(ValueError):
  """A --tracker value that cannot be understood."""


def parse(spec: str) -> dict:
  """The fields of a tracker spec (see the module docstring).

  Raises:
    TrackerSpecError: naming what is wrong.
  """
  if not spec.startswith(_SCHEME):
    raise TrackerSpecError(
      f'--tracker {spec!r}: expected natnet:SERVER[:PORT],rigid_body=ID,...'
    )
  address, *pairs = spec[len(_SCHEME) :].split(',')
  server, _, port = address.partition(':')
  if not server:
    raise TrackerSpecError(f'--tracker {spec!r}: no server address')
  fields = {'server': server}
  try:
    fields['command_port'] = int(port) if port else natnet.DEFAULT_COMMAND_PORT
  except ValueError:
    raise TrackerSpecError(f'--tracker: bad port {port!r}') from None
  for pair in pairs:
    key, sep, value = pair.partition('=')
    key = key.strip()
    if not sep or key not in _OPTIONS:
      raise TrackerSpecError(
        f'--tracker: unknown option {pair!r}; options are {list(_OPTIONS)}'
      )
    fields[key] = value.strip()
  if 'rigid_body' not in fields:
    raise TrackerSpecError('--tracker: rigid_body=ID (the torso) is required')
  try:
    fields['data_port'] = int(fields.get('data_port', natnet.DEFAULT_DATA_PORT))
    if 'version' in fields:
      major, _, minor = fields['version'].partition('.')
      fields['version'] = (int(major), int(minor or 0))
  except ValueError as error:
    raise TrackerSpecError(f'--tracker: {error}') from None
  y_up = fields.get('y_up', 'true').lower()
  if y_up not in ('true', 'false'):
    raise TrackerSpecError(f'--tracker: y_up must be true or false: {y_up}')
  fields['y_up'] = y_up == 'true'
  return fields


def make_tracker(spec: str) -> tracking.TorsoTracker:
  """A `TorsoTracker` on the NatNet stream a spec names.

  Raises:
    TrackerSpecError: for a malformed spec.
    OSError: if the socket cannot be opened.
  """
  fields = parse(spec)
  multicast = fields.get('multicast', natnet.DEFAULT_MULTICAST_GROUP)
  unicast = multicast == 'unicast'
  client = natnet.NatNetClient(
    multicast_group=None if unicast else multicast,
    data_port=fields['data_port'],
    local_interface=fields.get('local', '0.0.0.0'),
    server_address=fields['server'],
    command_port=fields['command_port'],
    version=fields.get('version'),
  )
  return tracking.TorsoTracker(
    client,
    fields['rigid_body'],
    target_body=fields.get('target'),
    heading_body=fields.get('heading'),
    frame_rotation=tracking.Y_UP_TO_Z_UP if fields['y_up'] else None,
  )
