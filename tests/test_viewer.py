"""nimbus-view: the viewer of a trained run (served on localhost, its scene, its renders, its refusals)."""

from __future__ import annotations

import http.client
import os
import shutil
import signal
import socket
import subprocess
import sys
import urllib.parse
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from nimbus.cli.train import main as train_main
from nimbus.cli.view import main as view_main
from nimbus.errors import NimbusError
from nimbus.train.checkpoint import CHECKPOINT
from nimbus.viewer import (LAYERS, ViewerConfig, camera_pose_wxyz, check_address, scaled_extinction, start_viewer,
                           viewer_camera)

QUICK = ["--preset", "tiny", "--set", "iterations=4", "--set", "checkpoint_interval=2", "--quiet"]


def _train(out: Path, method: str, *extra: str) -> Path:
    with pytest.raises(SystemExit) as info:
        train_main(["builtin:garden:tiny", "--method", method, *QUICK, *extra, "--out", str(out)])
    assert info.value.code == 0
    return out


@pytest.fixture(scope="module")
def nimbus_run(tmp_path_factory):
    """A NimbusGS run with every component, so T, P and R exist (stage 2 from iteration 3)."""
    return _train(tmp_path_factory.mktemp("runs") / "nimbus", "nimbus-full", "--set", "m_init=2")


@pytest.fixture(scope="module")
def viewer(nimbus_run):
    """The viewer of ``nimbus_run`` on a free port; ``viewer.files_before`` is the run folder before it opened."""
    files_before = snapshot(nimbus_run)
    v = start_viewer(nimbus_run, ViewerConfig(port=0, render_height=36))
    v.files_before = files_before
    yield v
    v.stop()


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _can_bind(port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            s.listen()
        except OSError:
            return False
    return True


# --- serving ------------------------------------------------------------------------------------
def test_answers_http_on_localhost(viewer):
    assert viewer.url.startswith(f"http://127.0.0.1:{viewer.port}/?token=") and viewer.port > 0
    with urllib.request.urlopen(viewer.url, timeout=30) as response:
        assert response.status == 200
        body = response.read()
    assert b"<html" in body[:2000].lower()


# --- who may connect: this machine's pages that know the printed URL -------------------------------
def _get(port: int, path: str, host: str | None = None, headers: dict | None = None) -> http.client.HTTPResponse:
    """``GET path`` from 127.0.0.1:``port`` with ``Host: host`` (default: the server's own address)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    conn.putrequest("GET", path, skip_host=True)
    conn.putheader("Host", host or f"127.0.0.1:{port}")
    for k, v in (headers or {}).items():
        conn.putheader(k, v)
    conn.endheaders()
    response = conn.getresponse()
    response.body = response.read()
    conn.close()
    return response


def _token(url: str) -> str:
    return urllib.parse.parse_qs(urllib.parse.urlsplit(url).query).get("token", [""])[0]


def _websocket(port: int, path: str = "/", origin: str | None = None, cookie: str | None = None):
    """A viser client's websocket handshake (its protocol version, our Origin and Cookie); the connection."""
    import viser
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{port}{path}", origin=origin, proxy=None, open_timeout=30,
                   subprotocols=[f"viser-v{viser.__version__}"], max_size=None,
                   additional_headers={"Cookie": cookie} if cookie else None)


def _refused(port: int, **kw) -> int:
    """The HTTP status a refused websocket handshake got (fails the test if it was accepted)."""
    from websockets.exceptions import InvalidStatus

    with pytest.raises(InvalidStatus) as info:
        _websocket(port, **kw).close()
    return info.value.response.status_code


def test_http_needs_the_token_and_the_servers_own_host_name(viewer):
    port, token = viewer.port, _token(viewer.url)
    # A page of another site that rebinds its name to 127.0.0.1 sends its own name as Host.
    assert _get(port, f"/?token={token}", host=f"evil.example:{port}").status == 403
    assert _get(port, f"/?token={token}", host="evil.example").status == 403
    assert _get(port, f"/?token={token}").status == 200
    assert _get(port, f"/?token={token}", host=f"localhost:{port}").status == 200
    assert len(token) >= 32
    for path in ("/", "/?token=", f"/?token={token[:-1]}", f"/?token={token}x", "/index.html"):
        refused = _get(port, path)
        assert refused.status == 403 and b"<html" not in refused.body.lower(), path


def test_websocket_needs_the_token_and_an_origin_of_this_viewer(viewer):
    port, token = viewer.port, _token(viewer.url)
    own = f"http://127.0.0.1:{port}"
    assert _refused(port, path=f"/?token={token}", origin="http://evil.example") == 403
    assert _refused(port, path=f"/?token={token}", origin=f"http://evil.example:{port}") == 403
    assert _refused(port, path=f"/?token={token}", origin="null") == 403
    assert _refused(port, origin=own) == 403
    assert _refused(port, path="/?token=wrong", origin=own) == 403
    assert _refused(port, origin=own, cookie=f"nimbus_view_{port}=wrong") == 403
    with _websocket(port, path=f"/?token={token}", origin=own) as ws:
        assert len(ws.recv(timeout=30)) > 0  # the scene's messages


def test_the_page_hands_its_token_to_its_websocket_by_cookie(viewer):
    """The browser loads the printed URL, keeps the cookie it is given, and opens the websocket to the bare
    address (viser's page drops the query): the cookie carries the token."""
    port = viewer.port
    page = _get(port, "/" + viewer.url.split("/", 3)[3])
    assert page.status == 200
    cookie = page.headers["Set-Cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    pair = cookie.split(";")[0]
    assert pair == f"nimbus_view_{port}={_token(viewer.url)}"
    assert _get(port, "/", headers={"Cookie": pair}).status == 200
    with _websocket(port, origin=f"http://localhost:{port}", cookie=pair) as ws:
        assert len(ws.recv(timeout=30)) > 0
    assert _refused(port, origin="http://evil.example", cookie=pair) == 403


def test_the_printed_url_opens_the_viewer(nimbus_run, tmp_path):
    """nimbus-view prints a URL with a fresh token that the server accepts; another launch gets another."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    tokens = []
    for i in range(2):
        with open(tmp_path / f"stderr{i}", "w") as err:
            proc = subprocess.Popen([sys.executable, "-m", "nimbus.cli.view", str(nimbus_run), "--port", "0",
                                     "--render-height", "12"], stdout=subprocess.PIPE, stderr=err, text=True, env=env)
        try:
            printed = []
            while len(printed) < 20 and not printed[-1:] == [""]:  # "" is the end: it stopped
                printed.append(proc.stdout.readline())
                if printed[-1].startswith("nimbus-view: open "):
                    break
            assert printed[-1].startswith("nimbus-view: open "), (printed, (tmp_path / f"stderr{i}").read_text())
            url = printed[-1].split()[2]
            port = urllib.parse.urlsplit(url).port
            with urllib.request.urlopen(url, timeout=30) as response:
                assert response.status == 200
            assert _get(port, "/").status == 403
            with _websocket(port, path="/?" + urllib.parse.urlsplit(url).query, origin=f"http://127.0.0.1:{port}") as ws:
                assert len(ws.recv(timeout=30)) > 0
            tokens.append(_token(url))
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
    assert tokens[0] != tokens[1]


def test_scene_holds_the_splats_and_one_frustum_per_view(viewer):
    scene = viewer.runner.scene
    assert viewer.nodes[0] == "/splats"
    frustums = viewer.nodes[1:]
    assert len(frustums) == len(scene.views) == len(set(frustums))
    assert sum(n.startswith("/cameras/test/") for n in frustums) == len(scene.test_views) > 0
    assert sum(n.startswith("/cameras/train/") for n in frustums) == len(scene.train_views) > 0
    assert viewer.splats.centers.shape == (viewer.runner.method.num_gaussians, 3)


def test_viewing_leaves_the_run_folder_as_it_was(viewer, nimbus_run):
    viewer.draw_frame()
    assert snapshot(nimbus_run) == viewer.files_before


# --- rendering ----------------------------------------------------------------------------------
def test_viewer_camera_is_our_camera_convention(viewer):
    """A training camera through viser's (wxyz, position, fov, aspect) and back is the same camera."""
    cam = viewer.runner.scene.train_views[1].camera
    back = viewer_camera(camera_pose_wxyz(cam), cam.center, cam.fov_y, cam.width / cam.height, cam.height)
    assert (back.width, back.height) == (cam.width, cam.height)
    np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera, atol=1e-9)
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [cam.fx, cam.fy, cam.cx, cam.cy], rtol=1e-9)
    ours = viewer.renderer.render(back)
    method = viewer.runner.method.render(cam)["rgb"].detach().numpy()
    np.testing.assert_allclose(ours, np.clip(method, 0, 1), atol=1e-5)


@pytest.mark.parametrize("layer", LAYERS)
def test_every_layer_renders_a_frame_of_the_camera(viewer, layer):
    assert viewer.renderer.layers == LAYERS
    cam = viewer_camera([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -2.0], 0.8, 4 / 3, 30)
    image = viewer.renderer.render(cam, layer)
    assert image.shape == (30, 40, 3) and image.dtype == np.float32
    assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1


def test_extinction_slider_rehazes_without_changing_the_model(viewer):
    method = viewer.runner.method
    cam = viewer.runner.scene.train_views[0].camera
    params = {k: v.clone() for k, v in method.medium.field.state_dict().items()}
    clean = viewer.renderer.render(cam, "clean")
    T = {f: viewer.renderer.render(cam, "T", extinction=f)[..., 0] for f in (0.0, 1.0, 3.0)}
    np.testing.assert_allclose(T[0.0], 1.0, atol=1e-4)  # no medium: everything arrives
    assert (T[3.0] <= T[1.0] + 1e-6).all() and T[3.0].mean() < T[1.0].mean()  # more extinction, less light
    np.testing.assert_allclose(viewer.renderer.render(cam, "degraded", extinction=0.0), clean, atol=1e-3)
    for k, v in method.medium.field.state_dict().items():
        assert torch.equal(v, params[k]), k
    with scaled_extinction(method.medium, 2.0):
        assert not torch.equal(method.medium.field.log_scale.detach(), params["log_scale"])
    assert torch.equal(method.medium.field.log_scale.detach(), params["log_scale"])


def test_residual_is_the_nearest_training_views(viewer):
    """At a training camera, R is what the method's protocol gives for that view."""
    method = viewer.runner.method
    cam = method.train_views[2].camera
    expected = method.render(cam, view_index=2)["residual"].detach().numpy()
    np.testing.assert_allclose(viewer.renderer.render(cam, "R"), np.clip(expected, 0, 1), atol=1e-6)


def test_a_frame_goes_to_the_panel_with_its_time(viewer):
    viewer.layer.value = "degraded"
    image = viewer.draw_frame()
    viewer.layer.value = "clean"
    assert image.shape[0] == 36 and viewer.image.image.shape == image.shape
    assert viewer.frame_s > 0 and "fps" in viewer.timing.content


def test_a_pixel_conditioned_airlight_renders_its_layers(tmp_path):
    """An airlight that reads the input's pixels (``airlight_input=pixel``, the paper's words), which a new camera
    has not: the viewer gives it the nearest training view's input, and at that view's own camera its P is the
    method's airlight layer."""
    # view_density off: the viewer renders with the field alone, a training view's own factor would differ.
    run = _train(tmp_path / "pixel", "nimbus-full", "--set", "m_init=2", "--set", "airlight_input=pixel",
                 "--set", "airlight_hidden=8", "--set", "view_density=false")
    v = start_viewer(run, ViewerConfig(port=0, render_height=12))
    try:
        method = v.runner.method
        assert method.medium.airlight.inputs == "pixel"
        for layer in ("degraded", "T", "P"):
            image = v.renderer.render(v.current_camera(), layer)
            assert np.isfinite(image).all() and image.shape[0] == 12
        cam = method.train_views[1].camera
        expected = method.render(cam, view_index=1)["airlight"].detach().numpy()
        np.testing.assert_allclose(v.renderer.render(cam, "P"), np.clip(expected, 0, 1), atol=1e-5)
    finally:
        v.stop()


def test_a_3dgs_run_shows_the_clean_render_only(tmp_path):
    run = _train(tmp_path / "gs", "3dgs")
    v = start_viewer(run, ViewerConfig(port=0, render_height=12))
    try:
        assert v.renderer.layers == ("clean",)
        cam = v.current_camera()
        assert v.renderer.render(cam).shape == (12, cam.width, 3)
        with pytest.raises(ValueError, match="layer"):
            v.renderer.render(cam, "T")
    finally:
        v.stop()


# --- refusals and stopping ----------------------------------------------------------------------
def test_non_local_bind_is_refused_unless_asked():
    with pytest.raises(NimbusError, match="--allow-remote"):
        check_address("0.0.0.0", 0, allow_remote=False)
    check_address("0.0.0.0", 0, allow_remote=True)
    check_address("localhost", 0, allow_remote=False)


def test_cli_refuses_a_non_local_host_in_one_line(nimbus_run, capsys):
    with pytest.raises(SystemExit) as info:
        view_main([str(nimbus_run), "--host", "0.0.0.0", "--port", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--allow-remote" in err[0]


def test_a_render_height_that_cannot_fit_is_refused_with_its_estimate(nimbus_run, capsys):
    """A frame's height is checked against memory at the first frame's aspect (4:3) before the server starts."""
    with pytest.raises(NimbusError, match=r"^--render-height=1000000 needs about [\d,]+ GiB for one frame at "
                                          r"1333333x1000000; the limit is .* GiB .*; use at most \d+$"):
        start_viewer(nimbus_run, ViewerConfig(port=0, render_height=1_000_000))
    with pytest.raises(SystemExit) as info:
        view_main([str(nimbus_run), "--port", "0", "--render-height", "100000"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --render-height=100000 needs about "), err


def test_busy_port_is_an_error_not_another_port(nimbus_run):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(NimbusError, match=f"port {port} .* in use"):
            start_viewer(nimbus_run, ViewerConfig(port=port))


def test_stop_frees_the_port_and_the_render_thread(nimbus_run):
    v = start_viewer(nimbus_run, ViewerConfig(port=0, render_height=12))
    port = v.port
    assert not _can_bind(port)
    with urllib.request.urlopen(v.url, timeout=30) as response:
        assert response.status == 200
    v.stop()
    assert not v._thread.is_alive()
    assert _can_bind(port)


@pytest.mark.parametrize("case", ["missing", "file", "empty", "corrupt"])
def test_bad_run_folder_is_one_error_line(nimbus_run, tmp_path, capsys, case):
    run = tmp_path / "run"
    if case == "file":
        run.write_text("not a folder")
    elif case == "empty":
        run.mkdir()
    elif case == "corrupt":
        shutil.copytree(nimbus_run, run)
        (run / CHECKPOINT).write_bytes(b"\x00garbage")
    with pytest.raises(SystemExit) as info:
        view_main([str(run), "--port", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert {"missing": "does not exist", "file": "not a run folder", "empty": "needs config.json",
            "corrupt": "checkpoint"}[case] in err[0]

