"""``python -m benchmark.bench_training``: the training-iteration table under the name issue 18 gave it.

The script itself is :mod:`benchmark.speed.training` (every speed script lives in ``benchmark/speed/``);
this module only runs it, with the same arguments.
"""

from benchmark.speed.training import main

if __name__ == "__main__":
    raise SystemExit(main())
