"""The one exception type that reaches users as a one-line message instead of a traceback."""


class UserError(Exception):
    """Bad input from the user: the message names the file, field or value and the fix."""
