"""The one user-facing error type of Nimbus.

Raise :class:`NimbusError` for anything a user can fix (a missing file, a bad
parameter, an unsupported camera model).  The command-line tools catch it and
print ``error: <message>`` with exit code 2 and no traceback.  Programming
errors keep raising their ordinary Python exceptions.

:class:`SkippedRecordWarning` is the one warning of the same kind: a record in a file of many (a line of a
results store) that does not fit its schema and was skipped, the rest being read.  The command-line tools
print it as one ``warning: <message>`` line.  It is not a ``UserWarning``, so code that silences the
routine ones (a store's truncated last line) still shows it.
"""

from __future__ import annotations


class NimbusError(Exception):
    """A problem with the user's input or request; the message says how to fix it."""


class SkippedRecordWarning(Warning):
    """A record that does not fit its schema was skipped; the message names the file, the line and the field."""
