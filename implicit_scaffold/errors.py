"""User-facing errors.

A :class:`ScaffoldError` carries one line that says what is wrong and how to fix
it; the command line prints that line and exits with code 2, no traceback.
"""


class ScaffoldError(ValueError):
    """Bad input or an impossible request, with a one-line message and its fix."""

    #: bytes: the --max-memory a refusal for memory names (None for any other error), so that a run
    #: refused by one stage can name the budget its later stages need too
    budget: int | None = None
    #: mm: the coarsest voxel that holds what a refusal for resolution found too thin (None for any other
    #: error), so that a caller that chose the voxel (design's cube) can choose again
    voxel: float | None = None

    @classmethod
    def for_budget(cls, message: str, budget) -> "ScaffoldError":
        """A refusal for memory naming `budget` (bytes) in `message`."""
        err = cls(message)
        err.budget = int(budget)
        return err

    @classmethod
    def for_voxel(cls, message: str, voxel: float) -> "ScaffoldError":
        """A refusal for resolution: `voxel` (mm) is the coarsest that would hold the geometry."""
        err = cls(message)
        err.voxel = float(voxel)
        return err


class OpenCLUnavailableError(ScaffoldError, RuntimeError):
    """No OpenCL platform or device could be found."""


class ScaffoldWarning(UserWarning):
    """Something was built, but not as asked: the message says what and how to fix it."""


def round_down(value: float) -> str:
    """`value` (mm) rounded down to 2 significant digits, as a message suggests a voxel: never coarser than it."""
    import math

    digits = 1 - int(math.floor(math.log10(abs(value))))
    return f"{math.floor(value * 10 ** digits) / 10 ** digits:g}"


def positive_mm(name: str, value, *, example: str | None = None) -> float:
    """`value` as a positive, finite length in mm, or a :class:`ScaffoldError` naming option `--name`.

    Parameters
    ----------
    name : str
        The command-line option, without its dashes (``voxel``, ``pixel``, ``pore-size``).
    value : object
    example : str, optional
        A value to suggest, e.g. ``"0.04"``.
    """
    import math

    hint = f"; e.g. --{name} {example}" if example else ""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--{name} must be a positive number of mm, got {value!r}{hint}") from None
    if not (math.isfinite(v) and v > 0):
        raise ScaffoldError(f"--{name} must be a positive number of mm, got {value!r}{hint}")
    return v
