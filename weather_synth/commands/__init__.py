"""Subcommands of ``nimbus-synth``: each module defines HELP, EXAMPLE, add_arguments(parser) and run(args).

What the subcommands share for their arguments lives here.
"""

from __future__ import annotations

import argparse

# Seeds every nimbus-synth command accepts: non-negative (weather_synth.config.SynthConfig's rule) and below
# 2**32, the largest seed every generator a command hands it to takes (COLMAP's is an unsigned 32-bit int;
# numpy and torch take more), so one rule holds for scene, sfm, degrade and demo alike.
MAX_SEED = 2**32 - 1


def seed_arg(text: str) -> int:
    """argparse type of ``--seed``: an integer in [0, MAX_SEED], else a usage error (exit 2, one line)."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"seed must be an integer in [0, {MAX_SEED}], got {text!r}") from None
    if not 0 <= seed <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"seed must be in [0, {MAX_SEED}], got {text}; pick a smaller "
                                         "non-negative seed")
    return seed
