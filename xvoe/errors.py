"""The one exception type for problems a user can fix (bad input, wrong files)."""

__all__ = ["XvoeError"]


class XvoeError(Exception):
    """Shown to the user as a one-line message; the command line exits with code 2."""
