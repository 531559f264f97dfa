"""The command lines that are only commands, on top of everything else.

`python -m robel_dm.tools.virtual_bus` serves a robot's motors on a virtual
Dynamixel bus; `python -m robel_dm.tools.view` opens the viewer. No module of
the package imports these (the import contract in `pyproject.toml` checks
it).
"""
