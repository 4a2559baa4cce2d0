"""Speed and measurement scripts, one per thing measured; each runs as ``python -m benchmark.speed.<name>``."""
