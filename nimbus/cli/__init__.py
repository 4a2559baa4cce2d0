"""Command-line tools that live in the ``nimbus`` package (``nimbus-train``, ``nimbus-view``)."""
