"""The benchmark harness (``nimbus-bench``: metrics, scoring of any method's renders, LPIPS weight set-up)
and speed / quality measurement scripts (run with ``python -m benchmark.speed.<name>``)."""
