"""Every transition of a session, recorded as it happens; read back later.

    env = recording.Recorder(suite.load('dclaw', 'turn_fixed'), 'runs/rec')
    ...  # reset and step as usual; close() finishes the file.
    episodes = recording.read('runs/rec')

A recording directory (the paths of LeRobotDataset v2.1):

  meta/info.json        format ('robel_dm-recording', version 1), fps, the
                        software versions (see robel_dm.provenance), the
                        robot configuration and the agent's observation keys
  meta/episodes.jsonl   one line per ended episode: episode_index, length,
                        complete (and the error that ended it), domain, task,
                        task_kwargs, the SHA-256 of its Parquet file, and
                        what the recorder was given (seed, policy, device
                        path ...; evaluate adds episode_seed, the seed of
                        the episode's reset)
  data/chunk-000/episode_<index>.parquet   a finished episode's steps
  data/chunk-000/episode_<index>.arrows    an episode being recorded (an
                        Arrow IPC stream, its metadata in the schema; partial
                        if the process died)

One row per dm_env timestep, the reset's first: `episode_index`,
`frame_index`, `timestamp` (physics time, s), `wall_time` (time.time()),
`step_type`, `action` (the normalized action that led to the row; NaN on the
first), `joint_targets` (what the actuators were told, rad), `next.reward`,
`discount`, `next.done`, `observation.<key>` for every observation,
`reward_terms.<name>`, and on a robot `motor.position`, `motor.velocity`,
`motor.current` (joint units) with `motor.timestamp` (time.monotonic()), and
`motor.temperature`, `motor.voltage`, `motor.hardware_error` with
`motor.health_timestamp` (read every `check_every` steps of the robot's
health limits, 10 by default). Parquet and Arrow files open
with pyarrow or pandas. Each file describes itself (schema metadata
`robel_dm.columns`; `describe_columns(path)` reads it from the file alone):
the domain and task, and every column's unit, shape per row and dimension
names (joint names, motor IDs, axes). The rows are timesteps, not
LeRobot's frames (the action taken from a frame's observation):
`lerobot.export` writes a LeRobotDataset (v3.0, or v2.1 for LeRobot 0.3).
docs/recording.md has the details.

Crash safety: steps are written to the episode's Arrow stream and flushed
(and fsynced) at least every 0.5 s, by a background thread when no step
comes, so after `kill -9` every step completed more than a second before is
readable, and the reader reports that episode with `complete: False` and the
metadata it started with. A kill while an episode is being finished, a
damaged Parquet file, stream or episodes.jsonl line cost at most that
episode (a stream: the rows from the damage on), with a warning naming the
file; the files carry checksums and are checked before a column is read
(docs/recording.md says what is and is not detected); no episode is read
twice. A directory holds one task: recording another into it raises
RecordingError (checked again under the directory's lock).
"""

from robel_dm.recording.format import (  # noqa: F401
  Episode,
  RecordingError,
)
from robel_dm.recording.reader import (  # noqa: F401
  describe_columns,
  read,
  summarize,
)
from robel_dm.recording.recorder import Recorder  # noqa: F401
