"""robel_dm: ROBEL's D'Claw and D'Kitty benchmarks on dm_control composer."""

__version__ = '0.1.0'
