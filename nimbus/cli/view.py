"""``nimbus-view``: look at a trained run in the browser (viser), on this machine only by default.

Examples::

    nimbus-view runs/garden-nimbus                  # then open the printed http://127.0.0.1:8080/?token=...
    nimbus-view runs/garden-nimbus --port 0         # any free port
    nimbus-view runs/garden-nimbus --host 0.0.0.0 --allow-remote   # reachable from other machines

The printed address holds a secret token drawn for this launch: requests without it are refused,
as are requests by another host name or from another site's page (see :mod:`nimbus.viewer`).
Ctrl-C (or a SIGTERM) stops the server.
"""

from __future__ import annotations

import signal
import sys
import threading
from typing import Sequence

from nimbus.cli_util import ArgumentParser, HelpFormatter, run_cli
from nimbus.viewer import DEFAULT_PORT, ViewerConfig


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog="nimbus-view", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("run", metavar="RUN", help="a nimbus-train run folder (its --out)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port; 0 picks a free one")
    p.add_argument("--host", default=ViewerConfig.host,
                   help="address to serve on; a non-local one needs --allow-remote")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow a --host other machines can reach (the viewer has no login)")
    p.add_argument("--render-height", type=int, default=ViewerConfig.render_height,
                   help="height in pixels of the frames Nimbus's renderer streams to the panel")
    p.add_argument("--device", default=ViewerConfig.device, help="torch device to render on: cpu or cuda[:N]")
    return p


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _main(argv: Sequence[str] | None) -> int:
    from nimbus.cli.train import parse_device
    from nimbus.viewer import start_viewer

    args = build_parser().parse_args(argv)
    device = parse_device(args.device)
    config = ViewerConfig(host=args.host, port=args.port, allow_remote=args.allow_remote,
                          render_height=args.render_height, device=str(device))
    viewer = start_viewer(args.run, config)
    # A kill (SIGTERM) stops the server as Ctrl-C does.
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        r, renderer, cam = viewer.runner, viewer.renderer, viewer.current_camera()
        print(f"{r.method_name} run {r.out}: iteration {r.iteration}, {r.method.num_gaussians} Gaussians; "
              f"layers: {', '.join(renderer.layers)}", file=sys.stderr)
        for layer in renderer.layers[:2]:  # clean, and degraded (the ray march) for NimbusGS
            frame = renderer.frame_time(cam, layer)
            print(f"render {cam.width}x{cam.height} {layer} on {config.device}: {1000 * frame:.0f} ms a frame "
                  f"({1 / max(frame, 1e-9):.1f} fps)", file=sys.stderr)
        print(f"nimbus-view: open {viewer.url} (Ctrl-C stops)", flush=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        print("nimbus-view: stopped", file=sys.stderr)
    finally:
        viewer.stop()
        signal.signal(signal.SIGTERM, previous)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    raise SystemExit(run_cli(_main, argv))


if __name__ == "__main__":
    main()
