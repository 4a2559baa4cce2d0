"""Developer and research scripts, run from a checkout with ``python -m tools.NAME`` (not installed)."""
