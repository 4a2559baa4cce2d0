"""``nimbus-view``'s viewer: a trained run in the browser (viser), drawn by the run's own method.

The run folder is opened read-only (:meth:`~nimbus.train.runner.Runner.open`: its ``config.json`` and
``checkpoint.pt``, read with ``torch.load(weights_only=True)``) and everything is shown in the
run's training frame (:class:`~nimbus.train.frame.SceneFrame`: centred on the cameras, extent 1).

The scene holds (:attr:`Viewer.nodes` lists the names):

- ``/splats``: the Gaussians as viser's Gaussian-splat primitive (centres, covariances, the colour of the SH DC
  band, opacities), drawn by the browser (WebGL);
- ``/cameras/train/NAME`` and ``/cameras/test/NAME``: one frustum per view, with its image downscaled.

The GUI panel streams frames of Nimbus's own renderer (:meth:`~nimbus.methods.base.Method.render`) from the
browser's current camera, and says how long one took.  For a NimbusGS run a ``layer`` dropdown switches
between the clean render, the degraded one (``I_hat T + P``: haze through the learned extinction field),
``T``, ``P`` and the residual ``R`` of the nearest training view (``R`` belongs to a training view, so it is
that view's, resized to the frame), and an ``extinction`` slider scales the extinction coefficient
at render time (0 clears the haze, 2 doubles it; the loaded model is left as it was).

The server binds 127.0.0.1 by default; another address is refused unless ``allow_remote`` is given,
since anyone who reaches the port sees the run.  Reaching the port is not enough either
(:class:`AccessGuard`): every launch draws a secret token, printed in the URL (``?token=...``), and
an HTTP request or websocket without it is refused (403).  The page hands the token on to its
websocket in a cookie (``HttpOnly``, ``SameSite=Strict``) that the server sets when it serves the
page.  On a loopback address the ``Host`` of every request must be one of this machine's own names
with the viewer's port (127.0.0.1, localhost, [::1]), so a web page whose name was rebound to
127.0.0.1 (DNS rebinding) is refused, and a websocket's ``Origin`` must be such an address too, so
a page of another site cannot open one from the user's browser.  Served to other machines
(``allow_remote``), the ``Host`` is whatever name they reach it by and the ``Origin`` must match it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hmac
import http
import inspect
import io
import ipaddress
import math
import secrets
import socket
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from nimbus.data import Camera
from nimbus.data.camera import rotation_from_quaternion_wxyz
from nimbus.data.images import to_uint8
from nimbus.errors import NimbusError
from nimbus.methods.nimbusgs.method import NimbusGS
from nimbus.methods.nimbusgs.degradation import Medium, compose
from nimbus.methods.nimbusgs.scattering import camera_rays
from nimbus.render.projection import covariance_3d
from nimbus.render.sh import sh_to_rgb
from nimbus.train.checkpoint import CHECKPOINT
from nimbus.train.runner import Runner
from nimbus.utils.memory import SizeCost, check_sizes

#: What the ``layer`` dropdown offers for a NimbusGS run (other runs: ``clean`` only).
LAYERS = ("clean", "degraded", "T", "P", "R")
#: The extinction slider's multiplier below which the medium counts as gone (log of 0 is -inf).
MIN_EXTINCTION_FACTOR = 1e-6
#: viser's own default port.
DEFAULT_PORT = 8080
#: The query parameter of the printed URL that carries the launch's secret token.
TOKEN_PARAM = "token"
#: Bytes of randomness in a token (:func:`secrets.token_urlsafe`; 43 characters).
TOKEN_BYTES = 32
#: The names of this machine a browser may use for a viewer on a loopback address.
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


@dataclasses.dataclass(frozen=True)
class ViewerConfig:
    """How :func:`start_viewer` serves a run.

    Attributes
    ----------
    host : str
        Address to bind (default 127.0.0.1: this machine only).
    port : int
        TCP port; 0 picks a free one.  A busy port is an error (viser would silently take the next one).
    allow_remote : bool
        Allow a ``host`` that is not a loopback address.
    render_height : int
        Height in pixels of the frames our renderer streams (the width follows the browser's aspect).
    thumbnail_side : int
        Longest side in pixels of the images on the camera frustums.
    frustum_scale : float
        Size of a frustum, in training-frame units (the scene has extent 1).
    device : str
        Torch device the run is loaded on and rendered with.
    """

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    allow_remote: bool = False
    render_height: int = 240
    thumbnail_side: int = 96
    frustum_scale: float = 0.06
    device: str = "cpu"


# --- address checks -----------------------------------------------------------------------------
def is_loopback(host: str) -> bool:
    """Whether every address ``host`` resolves to is a loopback one (NimbusError for an unknown host)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise NimbusError(f"--host {host!r} is not an address of this machine ({e}); leave --host out to "
                          "serve on 127.0.0.1") from None
    return all(ipaddress.ip_address(info[4][0].split("%")[0]).is_loopback for info in infos)


def check_address(host: str, port: int, allow_remote: bool) -> None:
    """Refuse a non-local ``host`` (unless ``allow_remote``), a port out of range, or a busy port."""
    if not is_loopback(host) and not allow_remote:
        raise NimbusError(f"--host {host} would serve the run to other machines, without any login; give "
                          "--allow-remote to do that on purpose, or leave --host out to serve on 127.0.0.1")
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise NimbusError(f"--port must be an integer in [0, 65535] (0: any free port), got {port!r}")
    if port == 0:
        return
    family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    with socket.socket(family, kind, proto) as probe:
        # As the server will bind: SO_REUSEADDR, so a port left in TIME_WAIT by a closed viewer is free.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as e:
            raise NimbusError(f"port {port} on {host} is in use ({e.strerror}); pick another --port, or --port 0 "
                              "for any free one") from None


def url_of(host: str, port: int) -> str:
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


# --- who may connect ------------------------------------------------------------------------------
class AccessGuard:
    """Decides which requests reach viser: those that carry the launch's token, by the viewer's own address.

    A request passes when all of these hold (module docstring):

    * it carries :attr:`token`, as ``?token=`` in its path or in the cookie :meth:`cookie_name`;
    * on a loopback bind, its ``Host`` is one of :data:`LOOPBACK_NAMES` (or the bound name) with the port;
    * its ``Origin``, when it has one (a browser's websocket always has), is ``http://`` and an accepted
      ``Host`` (on a remote bind: the request's own ``Host``).

    Parameters
    ----------
    host : str
        The address the server binds.
    loopback : bool
        Whether ``host`` is a loopback address (names of this machine only) or served to others.
    token : str, optional
        Default: a new :func:`secrets.token_urlsafe` of :data:`TOKEN_BYTES`.
    """

    def __init__(self, host: str, loopback: bool, token: str | None = None) -> None:
        self.host = host
        self.loopback = loopback
        self.token = token or secrets.token_urlsafe(TOKEN_BYTES)

    @staticmethod
    def cookie_name(port: int) -> str:
        """One cookie per port: cookies are scoped by host name, not port, and two viewers may run."""
        return f"nimbus_view_{port}"

    def accepted_hosts(self, port: int) -> set[str] | None:
        """The ``Host`` values accepted (lower case), None for any (a bind other machines reach)."""
        if not self.loopback:
            return None
        names = {*LOOPBACK_NAMES, self.host.lower() if ":" not in self.host else f"[{self.host.lower()}]"}
        return {f"{n}:{port}" for n in names} | (names if port == 80 else set())

    def refusal(self, request, port: int) -> str | None:
        """Why ``request`` (a websockets ``Request`` to ``port``) is refused, or None when it may pass."""
        headers = request.headers
        host = headers.get("Host", "").strip().lower()
        hosts = self.accepted_hosts(port)
        if not host or (hosts is not None and host not in hosts):
            return f"this viewer answers to its own address only (http://127.0.0.1:{port}), not {host or 'none'}"
        origin = headers.get("Origin")
        if origin is not None and origin.strip().lower() not in {f"http://{h}" for h in (hosts or {host})}:
            return "pages of other sites may not connect to this viewer"
        if not self._has_token(request, port):
            return "open the address nimbus-view printed, with its ?token=..."
        return None

    def _has_token(self, request, port: int) -> bool:
        query = urllib.parse.parse_qs(urllib.parse.urlsplit(request.path).query)
        given = query.get(TOKEN_PARAM, [])
        cookies = [c.split("=", 1) for h in request.headers.get_all("Cookie") for c in h.split(";") if "=" in c]
        given += [v.strip() for k, v in cookies if k.strip() == self.cookie_name(port)]
        return any(hmac.compare_digest(g.encode(), self.token.encode()) for g in given)

    def wrap(self, process_request):
        """websockets' ``process_request`` hook: refuse with 403, else call viser's own ``process_request``
        (which serves the page over HTTP), and give a browser that came with ``?token=`` its cookie."""
        async def guarded(connection, request):
            port = connection.local_address[1]
            reason = self.refusal(request, port)
            if reason is not None:
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"nimbus-view: {reason}\n")
            response = process_request(connection, request) if process_request is not None else None
            if inspect.isawaitable(response):
                response = await response
            if response is not None and response.status_code == http.HTTPStatus.OK:
                response.headers["Set-Cookie"] = (f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; "
                                                  "SameSite=Strict")
            return response

        return guarded


_SERVE_LOCK = threading.Lock()


@contextlib.contextmanager
def guarded_serving(guard: AccessGuard) -> Iterator[list]:
    """Inside the block, a websockets server that viser starts checks every request with ``guard``.

    viser takes no request hook of its own: its server thread calls ``websockets.asyncio.server.serve``
    with its HTTP handler as ``process_request``, before ``ViserServer()`` returns, so that function is
    wrapped for the duration of the block.  The list yielded gets one entry per server guarded: empty
    after the block means viser served some other way and the viewer must not run.  viser's banner
    (an address without the token, which would be refused) is kept off stdout.
    """
    import websockets.asyncio.server as ws_server

    original = ws_server.serve
    guarded: list = []

    def serve(*args, process_request=None, **kwargs):
        guarded.append(True)
        return original(*args, process_request=guard.wrap(process_request), **kwargs)

    with _SERVE_LOCK, contextlib.redirect_stdout(io.StringIO()):
        ws_server.serve = serve
        try:
            yield guarded
        finally:
            ws_server.serve = original


# --- cameras -------------------------------------------------------------------------------------
def viewer_camera(wxyz, position, fov_y: float, aspect: float, height: int) -> Camera:
    """Our :class:`Camera` of a viser camera: ``wxyz`` / ``position`` the camera-to-world pose (OpenCV axes,
    as viser's cameras are), ``fov_y`` the vertical field of view in radians, ``aspect`` width / height."""
    height = int(height)
    width = max(1, int(round(height * float(aspect))))
    focal = 0.5 * height / math.tan(0.5 * float(fov_y))
    R = rotation_from_quaternion_wxyz(np.asarray(wxyz, np.float64)).T
    return Camera(width, height, focal, focal, width / 2, height / 2, R, -R @ np.asarray(position, np.float64))


def camera_pose_wxyz(camera: Camera) -> np.ndarray:
    """The (w, x, y, z) quaternion of ``camera``'s camera-to-world rotation (viser's ``wxyz``)."""
    import viser.transforms as vtf

    return vtf.SO3.from_matrix(camera.R.T).wxyz


def nearest_view(camera: Camera, views) -> int:
    """Index of the view in ``views`` whose camera is closest to ``camera`` (centre distance, then direction)."""
    centers = np.array([v.camera.center for v in views])
    forward = np.array([v.camera.R[2] for v in views])
    cost = np.linalg.norm(centers - camera.center, axis=1) + 0.1 * (1.0 - forward @ camera.R[2])
    return int(np.argmin(cost))


def thumbnail(image: np.ndarray, side: int) -> np.ndarray:
    """``image`` (float [H, W, 3] in [0, 1]) as uint8 with its longest side at most ``side`` pixels."""
    h, w = image.shape[:2]
    f = min(1.0, side / max(h, w))
    small = cv2.resize(image, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    return to_uint8(small)


# --- rendering -----------------------------------------------------------------------------------
@contextlib.contextmanager
def scaled_extinction(medium: Medium, factor: float) -> Iterator[None]:
    """Inside the block the medium's extinction is ``factor`` times the learned one (its log density scale
    shifted by ``log(factor)``); the learned value is restored on the way out."""
    log_scale = medium.field.log_scale if medium.field is not None else medium.ext_log_scale
    saved = log_scale.detach().clone()
    with torch.no_grad():
        log_scale.add_(math.log(max(float(factor), MIN_EXTINCTION_FACTOR)))
    try:
        yield
    finally:
        with torch.no_grad():
            log_scale.copy_(saved)


class RunRenderer:
    """A run's method rendering any camera of the training frame in one of its :attr:`layers`.

    One frame at a time (the method is not thread-safe): the viewer's render thread and a caller
    share a lock.
    """

    def __init__(self, runner: Runner) -> None:
        self.method = runner.method
        self.views = list(self.method.train_views)
        self.layered = isinstance(self.method, NimbusGS)
        self.layers = LAYERS if self.layered else LAYERS[:1]
        self._lock = threading.Lock()

    @torch.no_grad()
    def render(self, camera: Camera, layer: str = "clean", extinction: float = 1.0) -> np.ndarray:
        """``camera``'s frame, float32 [H, W, 3] in [0, 1], as ``layer`` shows it (``T`` in grey)."""
        if layer not in self.layers:
            raise ValueError(f"layer {layer!r} is not one of {self.layers}")
        with self._lock:
            image = self._render(camera, layer, extinction)
        if image.shape[:2] != (camera.height, camera.width):
            image = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(np.clip(image, 0.0, 1.0), dtype=np.float32)

    def _render(self, camera: Camera, layer: str, extinction: float) -> np.ndarray:
        method = self.method
        vi = nearest_view(camera, self.views) if self.layered else None
        if layer == "R":  # a training view's own layer, through the method's protocol
            out = method.render(self.views[vi].camera, view_index=vi)
            return out["residual"].float().cpu().numpy()
        out = method.render(camera)
        if layer == "clean":
            return out["rgb"].float().cpu().numpy()
        T, P = self._medium(camera, out, vi, extinction)
        image = {"degraded": compose(out["rgb"], T, P), "T": T.expand_as(out["rgb"]), "P": P}[layer]
        return image.float().cpu().numpy()

    def _medium(self, camera: Camera, render: dict, vi: int, extinction: float) -> tuple:
        """``(T [H, W, 1], P [H, W, 3])`` of ``camera`` through the learned medium, the airlight conditioned on
        the nearest training view ``vi`` (NimbusGS's ``compose`` is written for training views only).  An
        airlight conditioned on the input's pixels (``airlight_input="pixel"``, nimbus-paper) has no input at a
        new camera: it gets view ``vi``'s input resized to the frame, an approximation that is exact only at
        that view."""
        method = self.method
        if method.medium is None:  # no CSM: nothing between the camera and the scene
            return torch.ones_like(render["rgb"][..., :1]), torch.zeros_like(render["rgb"])
        rays = camera_rays(camera, method.device)
        with scaled_extinction(method.medium, extinction):
            # The per-Gaussian extinction ablation has no field: its extinction is a render of the Gaussians.
            ext = method._extinction_image(camera) if method.medium.field is None else None
            image = F.interpolate(method.train_images[vi].permute(2, 0, 1)[None], size=(camera.height, camera.width),
                                  mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
            return method.medium.forward(rays, render, method.descriptors[vi], ext, image=image)

    def frame_time(self, camera: Camera, layer: str = "clean", repeats: int = 3) -> float:
        """Median seconds of one :meth:`render` of ``camera`` in ``layer`` (after one warm-up frame)."""
        self.render(camera, layer)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            self.render(camera, layer)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))


def splat_arrays(runner: Runner) -> dict[str, np.ndarray]:
    """The Gaussians as viser's splat primitive takes them: ``centers`` [N, 3], ``covariances`` [N, 3, 3],
    ``rgbs`` [N, 3] (the DC band's colour, clipped to [0, 1]) and ``opacities`` [N, 1]."""
    with torch.no_grad():
        g = runner.method.gaussians()
        return {
            "centers": g.means.float().cpu().numpy(),
            "covariances": covariance_3d(g.quats.float(), g.log_scales.float()).cpu().numpy(),
            "rgbs": sh_to_rgb(g.sh_dc[:, 0].float()).clamp(0.0, 1.0).cpu().numpy(),
            "opacities": g.opacities.float()[:, None].cpu().numpy(),
        }


# --- the viewer ----------------------------------------------------------------------------------
def open_run(run_dir: str | Path, device: str = "cpu") -> Runner:
    """The run in ``run_dir`` at its last checkpoint, read-only; NimbusError for what is not a run."""
    run = Path(run_dir)
    if not run.exists():
        raise NimbusError(f"run folder {run} does not exist; give the --out folder of a nimbus-train run")
    if not run.is_dir():
        raise NimbusError(f"{run} is a file, not a run folder; give the --out folder of a nimbus-train run")
    if not (run / "config.json").is_file() or not (run / CHECKPOINT).is_file():
        raise NimbusError(f"{run} is not a run folder of nimbus-train (it needs config.json and {CHECKPOINT}); "
                          "give the --out folder of a run that saved a checkpoint")
    return Runner.open(run, progress=False, device=torch.device(device))


@dataclasses.dataclass
class _View:
    """What the next frame is drawn from: the latest camera a browser reported."""

    wxyz: np.ndarray
    position: np.ndarray
    fov: float
    aspect: float


class Viewer:
    """A running viewer (built by :func:`start_viewer`): the viser server, the run and its renderer.

    Attributes
    ----------
    server : viser.ViserServer
    runner : Runner
        The opened run (training frame).
    renderer : RunRenderer
    nodes : list of str
        The scene nodes added (``/splats``, ``/cameras/train/NAME``, ``/cameras/test/NAME``).
    url : str
        The address to open, with the launch's token.
    guard : AccessGuard
    frame_s : float
        Seconds our renderer took for the last streamed frame.
    """

    def __init__(self, server, runner: Runner, config: ViewerConfig, guard: AccessGuard) -> None:
        self.server = server
        self.runner = runner
        self.config = config
        self.guard = guard
        self.renderer = RunRenderer(runner)
        self.nodes: list[str] = []
        self.url = f"{url_of(config.host, server.get_port())}/?{TOKEN_PARAM}={guard.token}"
        self.frame_s = float("nan")
        first = runner.scene.train_views[0].camera
        self._view = _View(camera_pose_wxyz(first), first.center, first.fov_y, first.width / first.height)
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._add_scene()
        self._add_gui()
        server.on_client_connect(self._on_connect)
        self._thread = threading.Thread(target=self._render_loop, name="nimbus-view-render", daemon=True)
        self._thread.start()
        self.request_frame()

    @property
    def port(self) -> int:
        return self.server.get_port()

    # --- scene ------------------------------------------------------------------------------
    def _add_scene(self) -> None:
        scene, c = self.runner.scene, self.config
        cams = [v.camera for v in scene.train_views]
        # The cameras' mean up (-y of OpenCV), so the browser orbits upright; start where training view 0 is.
        up = -np.mean([cam.R[1] for cam in cams], axis=0)
        up = up / max(np.linalg.norm(up), 1e-12)
        self.server.scene.set_up_direction(up)
        # Start behind and above training view 0, looking where it looks: its frustum, its neighbours and the
        # scene in sight (from view 0's own centre its frustum image would fill the window).
        first = cams[0]
        target = first.center + first.R[2] * self._look_distance(first)
        self.server.initial_camera.position = first.center + 0.6 * (first.center - target) + 0.3 * up
        self.server.initial_camera.look_at = target
        self.server.initial_camera.up = up
        self.server.initial_camera.fov = first.fov_y
        self.splats = self.server.scene.add_gaussian_splats("/splats", **splat_arrays(self.runner))
        self.nodes.append("/splats")
        test = scene.test_names
        for split, color in (("train", (40, 110, 230)), ("test", (235, 120, 20))):
            for view in scene.views:
                if (view.name in test) != (split == "test"):
                    continue
                cam = view.camera
                name = f"/cameras/{split}/{Path(view.name).stem}"
                self.server.scene.add_camera_frustum(
                    name, fov=cam.fov_y, aspect=cam.width / cam.height, scale=c.frustum_scale, color=color,
                    image=thumbnail(view.load_image(), c.thumbnail_side), wxyz=camera_pose_wxyz(cam),
                    position=cam.center, thickness=0.004)
                self.nodes.append(name)

    def _look_distance(self, camera: Camera) -> float:
        """Median depth of the sparse points in front of ``camera`` (1, the scene extent, if none)."""
        z = np.asarray(self.runner.scene.points, np.float64) @ camera.R[2] + camera.t[2]
        return float(np.median(z[z > 0])) if np.any(z > 0) else 1.0

    # --- GUI --------------------------------------------------------------------------------
    def _add_gui(self) -> None:
        gui, r = self.server.gui, self.runner
        gui.add_markdown(f"**{r.method_name}** run `{r.out.name}`: iteration {r.iteration}, "
                         f"{r.method.num_gaussians} Gaussians")
        self.layer = gui.add_dropdown("layer", self.renderer.layers, initial_value="clean",
                                      disabled=not self.renderer.layered,
                                      hint="NimbusGS: clean, degraded (I T + P), T, P, R of the nearest view")
        self.extinction = gui.add_slider("extinction x", min=0.0, max=4.0, step=0.05, initial_value=1.0,
                                         disabled=not (self.renderer.layered and r.method.medium is not None),
                                         hint="scales the learned extinction at render time (re-hazing)")
        self.show_splats = gui.add_checkbox("WebGL splats", initial_value=True)
        self.image = gui.add_image(np.zeros((self.config.render_height, self.config.render_height, 3), np.uint8),
                                   label="Nimbus render (this view)", format="jpeg")
        self.timing = gui.add_markdown("render: -")
        self.layer.on_update(lambda _: self.request_frame())
        self.extinction.on_update(lambda _: self.request_frame())
        self.show_splats.on_update(self._toggle_splats)

    def _toggle_splats(self, _event) -> None:
        self.splats.visible = bool(self.show_splats.value)

    # --- frames -----------------------------------------------------------------------------
    def _on_connect(self, client) -> None:
        client.camera.on_update(self._on_camera)
        self._on_camera(client.camera)

    def _on_camera(self, camera) -> None:
        self._view = _View(np.asarray(camera.wxyz), np.asarray(camera.position), float(camera.fov),
                           float(camera.aspect))
        self.request_frame()

    def request_frame(self) -> None:
        """Ask the render thread for a frame of the latest camera and GUI settings."""
        self._wake.set()

    def current_camera(self) -> Camera:
        v = self._view
        return viewer_camera(v.wxyz, v.position, v.fov, v.aspect, self.config.render_height)

    def draw_frame(self) -> np.ndarray:
        """Render the current camera with the GUI's settings, show it in the panel and return it."""
        t0 = time.perf_counter()
        image = self.renderer.render(self.current_camera(), self.layer.value, float(self.extinction.value))
        self.frame_s = time.perf_counter() - t0
        self.image.image = to_uint8(image)
        h, w = image.shape[:2]
        self.timing.content = (f"render {w}x{h} `{self.layer.value}`: {1000 * self.frame_s:.0f} ms "
                               f"({1 / max(self.frame_s, 1e-9):.1f} fps, {self.config.device})")
        return image

    def _render_loop(self) -> None:
        # Frames are drawn one at a time from the latest request: camera moves that arrive while a frame
        # renders collapse into the next one instead of queueing up.
        while True:
            self._wake.wait()
            if self._stopping.is_set():
                return
            self._wake.clear()
            try:
                self.draw_frame()
            except Exception as e:  # noqa: BLE001 - a failed frame is reported in the panel, the server stays up
                self.timing.content = f"render failed: {e.__class__.__name__}: {str(e)[:200]}"

    def stop(self) -> None:
        """Stop the render thread and the server (the port is free again when this returns)."""
        self._stopping.set()
        self._wake.set()
        self._thread.join()
        self.server.stop()


def check_render_height(runner: Runner, config: ViewerConfig) -> None:
    """Refuse a ``render_height`` whose frames cannot fit in memory (:func:`~nimbus.utils.memory.check_sizes`),
    at the first frame's aspect (training view 0's): the method's render of every layer, and the panel's image."""
    first = runner.scene.train_views[0].camera
    aspect = first.width / first.height

    def width(h: int) -> int:
        return max(1, round(h * aspect))

    def need(h: int) -> float:  # the render, and the panel's uint8 RGB image (its first, blank one is square)
        return runner.method.frame_bytes(h * width(h)) + 3.0 * h * max(h, width(h))

    check_sizes([SizeCost("--render-height", config.render_height, need, lambda h: f"one frame at {width(h)}x{h}")],
                torch.device(config.device))


def start_viewer(run_dir: str | Path, config: ViewerConfig = ViewerConfig()) -> Viewer:
    """Open the run in ``run_dir`` and serve it; the running :class:`Viewer` (call :meth:`Viewer.stop`).

    Raises NimbusError for a refused address (:func:`check_address`), a busy port, a folder that is
    not a readable run, or a render height whose frames cannot fit in memory (:func:`check_render_height`).
    """
    check_address(config.host, config.port, config.allow_remote)
    if config.render_height < 8:
        raise NimbusError(f"--render-height must be at least 8 pixels, got {config.render_height}")
    runner = open_run(run_dir, config.device)
    check_render_height(runner, config)
    import viser

    guard = AccessGuard(config.host, is_loopback(config.host))
    with guarded_serving(guard) as guarded:
        server = viser.ViserServer(host=config.host, port=config.port, verbose=False)
    if not guarded:
        server.stop()
        raise NimbusError(f"viser {viser.__version__} serves in a way nimbus-view cannot guard with its token; "
                          "install the viser version of Nimbus's constraints.txt")
    if config.port and server.get_port() != config.port:  # taken between the check and the bind
        server.stop()
        raise NimbusError(f"port {config.port} on {config.host} is in use; pick another --port, or --port 0 "
                          "for any free one")
    try:
        return Viewer(server, runner, config, guard)
    except BaseException:
        server.stop()
        raise
