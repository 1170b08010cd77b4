"""User-facing errors.

A :class:`ScaffoldError` carries one line that says what is wrong and how to fix
it; the command line prints that line and exits with code 2, no traceback.
"""


class ScaffoldError(ValueError):
    """Bad input or an impossible request, with a one-line message and its fix."""


class OpenCLUnavailableError(ScaffoldError, RuntimeError):
    """No OpenCL platform or device could be found."""
