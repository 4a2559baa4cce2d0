"""Speed and measurement scripts, one per thing measured; each runs as ``python -m tools.speed.<name>`` from a checkout."""
