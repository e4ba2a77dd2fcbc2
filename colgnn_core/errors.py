"""Exceptions shared by the whole package.

`InputError` marks bad user input (unknown scene, malformed file, invalid pose,
...). The CLI turns it into exit code 2 and a one-line message; library callers
can catch it and keep their state.
"""


class InputError(ValueError):
    """Bad input from a user or a file. The message names the problem."""


class SimulationError(RuntimeError):
    """The ground-truth solver could not produce a verified frame."""
