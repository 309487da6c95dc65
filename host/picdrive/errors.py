"""Base class of the errors picdrive reports to the user.

The CLI prints these as one line, ``picdrive: error: <message>``, and exits
with status 2; any other exception is a bug and shows its traceback.
"""


class PicdriveError(Exception):
    """An error caused by the user's input or environment, with a message
    that names the problem and the fix."""
