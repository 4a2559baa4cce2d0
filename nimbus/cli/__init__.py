"""Command-line tools that live in the ``nimbus`` package (``nimbus-train``, ``nimbus-view``).

Importing this package (every Nimbus command does, first: ``nimbus-synth`` and ``nimbus-bench`` too) sets
``OMP_WAIT_POLICY=PASSIVE`` unless the user set it: OpenMP's default spin-waiting makes torch 10-40x slower on 2
threads when another process shares the cores (measured on the 2-core CI machine), while passive waiting costs
little on an idle machine.  It only takes effect before torch is loaded, hence here and not in ``main()``; the
library itself (``import nimbus``) leaves the environment alone.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
