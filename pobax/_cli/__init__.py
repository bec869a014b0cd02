"""The command line's implementation; `cli.py` at the repository root is its entry point (parsing the command,
running it, its errors and exit codes).

- `commands`: the commands' dataclasses, whose fields are the flags and whose docstrings are the help.
- `args`: reading a command's flags (the training flags given, the configuration, devices, a multi-process run).
- `training`: running the commands that train (train, sweep, gap, benchmark) and printing what they report.
- `inspection`: running the commands that read runs or the registry (results, plot, eval, render, envs).
"""
