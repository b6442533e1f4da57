"""The one root of the errors ddarm reports by name: refused input, or a run that could not be trusted.

Every such error's message says what is wrong (the parameter, joint, path or node); the `ddarm`
command prints it on one line and exits 2. Anything else that escapes is a bug, and shows its traceback.
"""


class DdarmError(Exception):
    """Refused input or a failed run, named in the message."""

