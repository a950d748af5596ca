"""The one exception type for user mistakes (bad files, bad arguments, degenerate scenes).

The CLI prints its message as a single line and exits with status 2, without a traceback. Messages
name the file and, where there is one, the row: ``poses.csv row 7: lower bound > upper bound``.
"""


class InputError(ValueError):
    """A problem with what the user gave us, explained in one line."""
