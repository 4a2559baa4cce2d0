"""The one user-facing error type of Nimbus.

Raise :class:`NimbusError` for anything a user can fix (a missing file, a bad
parameter, an unsupported camera model).  The command-line tools catch it and
print ``error: <message>`` with exit code 2 and no traceback.  Programming
errors keep raising their ordinary Python exceptions.
"""

from __future__ import annotations


class NimbusError(Exception):
    """A problem with the user's input or request; the message says how to fix it."""
