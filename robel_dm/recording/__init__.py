"""Every transition of a session, recorded as it happens; read back later.

    env = recording.Recorder(suite.load('dclaw', 'turn_fixed'), 'runs/rec')
    ...  # reset and step as usual; close() finishes the file.
    episodes = recording.read('runs/rec')

A recording directory (LeRobotDataset v3's layout where it fits):

  meta/info.json        format ('robel_dm-recording', version 1), fps, the
                        software versions (see robel_dm.provenance)
  meta/episodes.jsonl   one line per ended episode: episode_index, length,
                        complete, domain, task, task_kwargs, and what the
                        recorder was given (seed, policy, device path ...)
  data/chunk-000/episode_<index>.parquet   a finished episode's steps
  data/chunk-000/episode_<index>.arrows    an episode being recorded (an
                        Arrow IPC stream; partial if the process died)

One row per timestep, the reset's first: `episode_index`, `frame_index`,
`timestamp` (physics time, s), `wall_time` (time.time()), `step_type`,
`action` (the normalized action that led to the row; NaN on the first),
`joint_targets` (what the actuators were told, rad), `next.reward`,
`discount`, `next.done`, `observation.<key>` for every observation,
`reward_terms.<name>`, and on a robot `motor.position`, `motor.velocity`,
`motor.current` (joint units) with `motor.timestamp` (time.monotonic()).
Parquet and Arrow files open with pyarrow or pandas; the column names follow
LeRobot's, but the directory is not a LeRobotDataset (no videos, stats or
task table).

Crash safety: steps are written to the episode's Arrow stream and flushed
at least once a second, so after `kill -9` every step completed more than a
second before is readable, and the reader reports that episode with
`complete: False`.
"""

from robel_dm.recording.format import (  # noqa: F401
  FORMAT,
  MIN_FREE_BYTES,
  Episode,
  RecordingError,
  read,
  summarize,
)
from robel_dm.recording.recorder import Recorder  # noqa: F401
