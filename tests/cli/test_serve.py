"""``lp3d serve``: the web app's API over HTTP and its WebSocket (one server, in-process, on a free
loopback port, with the shipped model), and one headless-Chromium session that uploads a photo and
streams a webcam fed from a ``.y4m`` file of teacher renders: both heads the page draws equal
``lp3d_render.render`` of the planes it drew within 1e-3 on a probe view, and those planes are the
server's (the photo's ``.npz`` download).

CI cost, measured on a 2-core machine shared with other jobs (lavapipe, SwiftShader): about 45 s in
all, of which the refinement test takes about 20 s (it imports PyTorch), the browser test about 16 s
(one browser, two 32² probe renders at 24+24 samples, 128² webcam frames) and the rest under 10 s.
"""

from __future__ import annotations

import base64
import io
import json
import os
import struct
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import lp3d_render
from lp3d.images import rgb_to_uint8
from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
from lp3d.render.camera import look_at_camera
from lp3d.render.native import native_triplane
from lp3d.render.triplane_io import load_triplane
from lp3d.serve import Server, make_state, missing_extra
from lp3d.serve.lifting import MAX_FRAME_BYTES, MESSAGE_MAGIC
from lp3d.serve.page import SERVE_PROBE_SETTINGS
from lp3d.share import viewer_scripts
from lp3d.teachers.procedural import ProceduralTeacher
from support.browser import BrowserError, Chromium
from support.cli import run

#: The browser's image against lp3d_render's, RGB in [-1, 1].
MAX_PROBE_ERROR = 1e-3
#: The probe's view (yaw, pitch in degrees).
PROBE_VIEW = (30.0, -10.0)

if (_why := missing_extra()) is not None:
    pytest.fail(_why, pytrace=False)  # the serve extra is part of ./dev setup: never a silent skip


def teacher_render(seed: int, yaw: float = 0.0, size: int = 128) -> np.ndarray:
    """A procedural teacher head seen from ``yaw``: (size, size, 3) uint8, framed as the encoder's
    training renders (a portrait crop: no face detection needed)."""
    tri = ProceduralTeacher(resolution=64).sample(seed)
    out = lp3d_render.render(
        native_triplane(tri),
        look_at_camera(yaw_deg=yaw),
        resolution=size,
        depth_resolution=24,
        depth_resolution_importance=24,
        outputs=["rgb"],
    )
    return rgb_to_uint8(out["rgb"])


def png_bytes(rgb: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format="PNG")
    return buffer.getvalue()


def parse_message(body: bytes) -> tuple[dict, np.ndarray]:
    """A triplane message -> (header, planes (3, 32, H, W) float16)."""
    assert body[:4] == MESSAGE_MAGIC
    (n,) = struct.unpack_from("<I", body, 4)
    header = json.loads(body[8 : 8 + n])
    h, w = header["height"], header["width"]
    texels = np.frombuffer(body[8 + n :], "<f2").reshape(3, h, w, 32)
    return header, texels.transpose(0, 3, 1, 2)


@pytest.fixture(scope="module")
def server():
    """The app with the shipped model on a free loopback port, in a thread of this process."""
    state = make_state(load_encoder(DEFAULT_MODEL))
    running = Server(state, "127.0.0.1", 0).start()
    yield running
    running.stop()


@pytest.fixture(scope="module")
def photo() -> bytes:
    return png_bytes(teacher_render(1_000_003))


def http(server: Server, path: str, body: bytes | None = None, headers: dict | None = None):
    """``(status, headers, body)`` of one request to ``server``."""
    request = urllib.request.Request(
        f"http://127.0.0.1:{server.port}{path}", data=body, headers=headers or {}
    )
    try:
        with urllib.request.urlopen(request, timeout=60) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read()


def ws_connect(server: Server, **kwargs):
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{server.port}/ws/live", max_size=None, open_timeout=30, **kwargs)


def frame_message(i: int, image: bytes) -> bytes:
    return struct.pack("<I", i) + image


def test_the_page_reuses_the_share_renderer_under_its_policy(server) -> None:
    status, headers, body = http(server, "/")
    page = body.decode()
    assert status == 200 and "lp3d serve" in page
    policy = headers["Content-Security-Policy"]
    assert policy.startswith("default-src 'none'; script-src 'sha256-") and "frame-ancestors 'none'" in policy
    assert "connect-src 'self'" in policy and "unsafe-eval" not in policy
    assert all(script in page for script in viewer_scripts())  # lp3d share's gpu.js and viewer.js
    assert page.count("<script") == 2 and "src=" not in page  # nothing fetched from elsewhere
    # Another site's page may not drive the server, nor a rebound DNS name reach it.
    assert http(server, "/", headers={"Origin": "http://evil.example"})[0] == 403
    assert http(server, "/", headers={"Host": "evil.example"})[0] == 403


def test_photo_upload_lifts_it_and_the_downloads_hold_what_the_page_draws(server, photo, tmp_path) -> None:
    status, _, body = http(server, "/api/photo?detect=0&name=teacher.png", photo)
    assert status == 200, body[:300]
    header, planes = parse_message(body)
    assert header["kind"] == "photo" and planes.shape == (3, 32, 64, 64)
    assert "centre crop" in header["description"] and header["timings_ms"]["encode"] > 0
    status, headers, npz = http(server, f"/api/photo/{header['id']}.npz")
    assert status == 200 and "attachment" in headers["Content-Disposition"]
    (tmp_path / "head.npz").write_bytes(npz)
    tri = load_triplane(tmp_path / "head.npz")
    assert tri.planes.dtype == np.float16
    np.testing.assert_array_equal(tri.planes, planes)
    status, _, page = http(server, f"/api/photo/{header['id']}.html")
    assert status == 200 and b'"format":"lp3d-share"' in page
    assert http(server, "/api/photo/nosuchid.npz")[0] == 404
    assert http(server, f"/api/photo/{header['id']}.exe")[0] == 404


def test_the_mesh_and_orbit_downloads_are_the_lifted_head(server, photo, tmp_path) -> None:
    import io

    import trimesh
    from PIL import Image, ImageSequence

    from lp3d.images import rgb_to_uint8
    from lp3d.render.camera import look_at_camera, orbit_angles
    from lp3d.render.mesh import extract_mesh
    from lp3d.render.native import render
    from lp3d.serve.downloads import ORBIT

    status, _, body = http(server, "/api/photo?detect=0&name=teacher.png", photo)
    assert status == 200, body[:300]
    pid = parse_message(body)[0]["id"]
    (tmp_path / "head.npz").write_bytes(http(server, f"/api/photo/{pid}.npz")[2])
    tri = load_triplane(tmp_path / "head.npz")
    status, headers, glb = http(server, f"/api/photo/{pid}.glb")
    assert status == 200 and headers["Content-Type"] == "model/gltf-binary"
    assert 'filename="teacher.glb"' in headers["Content-Disposition"]
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh", process=False)
    want = extract_mesh(tri)
    assert len(want.vertices) > 1000
    np.testing.assert_allclose(np.asarray(mesh.vertices), want.vertices, rtol=0, atol=1e-6)
    status, headers, gif = http(server, f"/api/photo/{pid}.gif")
    assert status == 200 and headers["Content-Type"] == "image/gif"
    frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(io.BytesIO(gif)))]
    assert len(frames) == ORBIT.frames and frames[0].shape == (ORBIT.resolution, ORBIT.resolution, 3)
    yaw, pitch = orbit_angles(ORBIT.frames, ORBIT.yaw_range, 0.0)[5]
    cam = look_at_camera(yaw_deg=yaw, pitch_deg=pitch)
    coarse, fine = ORBIT.samples
    rgb = render(
        tri, cam, resolution=ORBIT.resolution, depth_resolution=coarse, depth_resolution_importance=fine
    )["rgb"]
    # A GIF holds 256 colours per frame: its frame is the render up to that quantisation.
    diff = np.abs(frames[5].astype(int) - rgb_to_uint8(rgb).astype(int))
    assert diff.mean() < 3.0, diff.mean()


def test_bad_uploads_get_a_clear_answer(server, photo, photos) -> None:
    cases = {
        "notes.jpg": (photos["text"].read_bytes(), 400, "not an image file"),
        "huge.png": (photos["huge"].read_bytes(), 400, "MP limit"),
        "empty.png": (b"", 400, "empty file"),
        "gradient.png": (photos["noface"].read_bytes(), 400, "no face found"),
    }
    for name, (data, code, words) in cases.items():
        status, _, body = http(server, f"/api/photo?name={name}", data)
        assert status == code and words in json.loads(body)["error"] and name in json.loads(body)["error"]
    limit, server.state.max_upload_bytes = server.state.max_upload_bytes, 1000
    try:
        status, _, body = http(server, "/api/photo?name=big.png", photo)
    finally:
        server.state.max_upload_bytes = limit
    assert status == 413 and "upload limit" in json.loads(body)["error"]
    # A detect flag that is neither 0 nor 1 was taken as "detect".
    status, _, body = http(server, "/api/photo?detect=banana", photo)
    assert status == 400 and json.loads(body)["error"] == "detect: must be 0 or 1"
    # A real photo of a face, found and aligned by the photo pipeline.
    status, _, body = http(server, "/api/photo?name=astronaut.jpg", photos["face"].read_bytes())
    assert status == 200 and "face" in parse_message(body)[0]["description"]


def test_refine_reports_progress_and_replaces_the_photos_head(server, photos) -> None:
    status, _, body = http(server, "/api/photo?name=astronaut.jpg", photos["face"].read_bytes())
    header, planes = parse_message(body)
    pid = header["id"]
    assert http(server, f"/api/photo/{pid}/refine?steps=0", b"")[0] == 400
    status, _, body = http(server, f"/api/photo/{pid}/refine?steps=1", b"")
    assert status == 202 and json.loads(body)["total"] == 1  # the pose is the face's: no pose steps
    deadline = time.monotonic() + 120
    while (progress := json.loads(http(server, f"/api/photo/{pid}/refine")[2]))["state"] not in (
        "done",
        "failed",
    ):
        assert time.monotonic() < deadline, progress
        time.sleep(0.2)
    assert progress["state"] == "done" and progress["step"] == 1, progress
    refined = parse_message(http(server, f"/api/photo/{pid}/triplane")[2])[1]
    assert refined.shape == planes.shape and not np.array_equal(refined, planes)


def test_live_frames_come_back_as_triplanes_newest_first(server, photo) -> None:
    """A burst of frames: every answer is a newer frame than the one before, the newest frame is
    always answered, and frames overtaken before they started were dropped (counted)."""
    with ws_connect(server) as ws:
        for i in range(12):
            ws.send(frame_message(i, photo))
        answered, dropped = [], 0
        while 11 not in answered or len(answered) + dropped < 12:
            header, planes = parse_message(ws.recv(timeout=60))
            assert header["kind"] == "live" and planes.shape == (3, 32, 64, 64)
            answered.append(header["frame"])
            dropped = max(dropped, header["dropped"])
        assert dropped > 0 and len(set(answered)) == len(answered) == 12 - dropped, (answered, dropped)
        # A frame that is not an image gets a message and the stream goes on.
        ws.send(frame_message(12, b"not an image at all"))
        assert "not an image file" in json.loads(ws.recv(timeout=60))["error"]
        ws.send(frame_message(13, photo))
        assert parse_message(ws.recv(timeout=60))[0]["frame"] == 13


def test_live_frames_of_a_face_follow_it(server, photos) -> None:
    """Each frame's face is found and aligned as a photo's: the same picture, the same pose, and the
    steadied crop stays on it."""
    face = photos["face"].read_bytes()
    with ws_connect(server) as ws:
        headers = []
        for i in range(3):
            ws.send(frame_message(i, face))
            headers.append(parse_message(ws.recv(timeout=60))[0])
    assert all(h["face"] for h in headers)
    assert headers[0]["pose"] == headers[1]["pose"] == headers[2]["pose"]


def test_live_limits_close_the_stream_with_a_reason(server, photo) -> None:
    from websockets.exceptions import ConnectionClosed

    def closed_by(messages: list) -> tuple[int, str]:
        with ws_connect(server) as ws:
            try:
                for m in messages:
                    ws.send(m)
                while True:
                    ws.recv(timeout=60)
            except ConnectionClosed as e:
                return e.rcvd.code, e.rcvd.reason

    assert closed_by([b"\0" * (MAX_FRAME_BYTES + 1)])[0] == 1009
    assert closed_by(["text is not a frame"]) == (1003, "frames are binary messages")
    # Far past a second's burst: the bucket refills while the server reads, and a loaded machine reads slowly.
    code, reason = closed_by([frame_message(i, b"x") for i in range(3000)])
    assert code == 1008 and "messages a second" in reason


def test_disconnects_mid_frame_and_four_clients_at_once(server, photo) -> None:
    """Clients that leave while their frame is being lifted do not disturb the server; four clients
    streaming together are each answered."""
    for _ in range(3):
        with ws_connect(server) as ws:
            ws.send(frame_message(0, photo))  # and gone at once, before its answer
    answers: dict[int, list[int]] = {}

    def client(k: int) -> None:
        with ws_connect(server) as ws:
            got = answers.setdefault(k, [])
            for i in range(3):
                ws.send(frame_message(i, photo))
                got.append(parse_message(ws.recv(timeout=120))[0]["frame"])

    threads = [threading.Thread(target=client, args=(k,)) for k in range(4)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=180)
    assert answers == {k: [0, 1, 2] for k in range(4)}, answers
    print(f"four clients, three frames each: {time.perf_counter() - t0:.2f} s")
    assert http(server, "/")[0] == 200 and server.state.live_clients == 0


def test_serve_refuses_another_host_without_allow_remote(capsys) -> None:
    code, out, _ = run(capsys, "serve", "--help")
    assert code == 0 and out.startswith("usage: lp3d serve") and "--allow-remote" in out
    code, _, err = run(capsys, "serve", "--host", "0.0.0.0", "--port", "0")
    assert code == 1 and "--allow-remote" in err and "not loopback" in err


def test_a_remote_server_needs_its_token(photo) -> None:
    """Off loopback every request needs the token (the page's address carries it)."""
    state = make_state(load_encoder(DEFAULT_MODEL), token="secret-token", loopback=False, refine=False)
    running = Server(state, "127.0.0.1", 0).start()
    try:
        assert running.url().endswith("/?token=secret-token")
        assert http(running, "/")[0] == 403
        assert http(running, "/?token=wrong")[0] == 403
        assert http(running, "/?token=secret-token")[0] == 200
        assert http(running, "/api/photo?detect=0", photo, {"X-LP3D-Token": "secret-token"})[0] == 200
        with pytest.raises(Exception, match="403|1008"):
            ws_connect(running).recv(timeout=30)
    finally:
        running.stop()


# ------------------------------------------------------------------------------- in a real browser


def write_y4m(path: Path, frames: list[np.ndarray], fps: int = 10) -> None:
    """An uncompressed 4:2:0 video (Chromium's fake webcam reads .y4m), BT.601 full range."""
    h, w = frames[0].shape[:2]
    with open(path, "wb") as f:
        f.write(f"YUV4MPEG2 W{w} H{h} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for rgb in frames:
            r, g, b = (rgb[..., i].astype(np.float64) for i in range(3))
            y = 0.299 * r + 0.587 * g + 0.114 * b
            u = 128 + (b - y) * 0.564
            v = 128 + (r - y) * 0.713
            half = lambda c: c.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))  # noqa: E731
            f.write(b"FRAME\n")
            for plane in (y, half(u), half(v)):
                f.write(np.clip(np.round(plane), 0, 255).astype(np.uint8).tobytes())


def probe_line(browser: Chromium, session: str, kind: str) -> dict:
    prefix = "LP3D_SERVE_PROBE "
    line = browser.wait_console(
        session, lambda t: t.startswith(prefix) and json.loads(t[len(prefix) :])["kind"] == kind, timeout=300
    )
    return json.loads(line[len(prefix) :])


def check_probe(probe: dict, server: Server) -> np.ndarray:
    """The page's probe image against lp3d_render.render of the planes the page drew (the server's
    decoder and bounds); returns those planes."""
    r = SERVE_PROBE_SETTINGS.resolution
    image = np.frombuffer(base64.b64decode(probe["rgb"]), "<f4").reshape(3, r, r)
    texels = np.frombuffer(base64.b64decode(probe["planes"]), "<f2")
    planes = texels.reshape(3, probe["height"], probe["width"], 32).transpose(0, 3, 1, 2)
    tri = server.state.lifter.package.triplane(np.ascontiguousarray(planes))
    camera = look_at_camera(yaw_deg=PROBE_VIEW[0], pitch_deg=PROBE_VIEW[1])
    kwargs = SERVE_PROBE_SETTINGS.native_kwargs()
    expected = lp3d_render.render(native_triplane(tri), camera, outputs=["rgb"], **kwargs)["rgb"]
    error = np.abs(image - expected).max()
    print(f"{probe['kind']} probe: max abs error {error:.2e}, {probe['ms']:.0f} ms in the browser")
    assert error <= MAX_PROBE_ERROR
    assert expected.std() > 0.05  # a head, not an empty image
    return planes


# Long because: one browser session, photo then live then a bad file, read top to bottom.
def test_browser_draws_the_uploaded_photo_and_the_live_stream(server, tmp_path) -> None:
    photo_path = tmp_path / "teacher.png"
    photo_path.write_bytes(png_bytes(teacher_render(1_000_003)))
    (tmp_path / "notes.png").write_text("this is not an image\n")
    y4m = tmp_path / "webcam.y4m"
    write_y4m(y4m, [teacher_render(1_000_004, yaw) for yaw in (-10.0, 0.0, 10.0)])
    flags = (
        "--use-fake-ui-for-media-stream",
        "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-video-capture={y4m}",
    )
    try:
        browser = Chromium(extra_flags=flags)
    except BrowserError as e:
        pytest.fail(str(e))
    with browser:
        yaw, pitch = PROBE_VIEW
        session = browser.open(f"http://127.0.0.1:{server.port}/#probe={yaw:g},{pitch:g}")
        browser.wait_console(session, lambda t: t == "LP3D_READY", timeout=60)
        browser.click(session, "#detect")  # the teacher's render is a portrait crop already

        def choose(path: Path) -> None:
            root = browser.call("DOM.getDocument", session=session)["root"]["nodeId"]
            node = browser.call("DOM.querySelector", {"nodeId": root, "selector": "#file"}, session=session)
            browser.call(
                "DOM.setFileInputFiles", {"files": [str(path)], "nodeId": node["nodeId"]}, session=session
            )

        choose(photo_path)
        photo_probe = probe_line(browser, session, "photo")
        planes = check_probe(photo_probe, server)
        status, _, npz = http(server, f"/api/photo/{photo_probe['id']}.npz")
        (tmp_path / "head.npz").write_bytes(npz)
        np.testing.assert_array_equal(load_triplane(tmp_path / "head.npz").planes, planes)

        browser.click(session, "#live")
        check_probe(probe_line(browser, session, "live"), server)
        stats = browser.wait_console(
            session, lambda t: t.startswith("LP3D_LIVE ") and json.loads(t[10:])["fps"] > 0, timeout=120
        )
        print("live:", stats)
        choose(tmp_path / "notes.png")
        browser.wait_console(session, lambda t: t.startswith("LP3D_MESSAGE ") and "not an image" in t, 60)
        if target := os.environ.get("LP3D_SERVE_SCREENSHOT"):
            screenshot(browser, server, Path(target), photos_face=photo_path)


def screenshot(browser: Chromium, server: Server, target: Path, photos_face: Path) -> None:
    """``LP3D_SERVE_SCREENSHOT=docs/serve.png`` (how ``docs/serve.png`` was made): the page in normal
    mode after a photo and a few seconds of webcam, at its final quality; prints the page's frame
    times per rung (its render rate on this browser's WebGPU)."""
    from skimage.data import astronaut

    astronaut_path = photos_face.with_name("astronaut.jpg")
    Image.fromarray(astronaut()).save(astronaut_path, quality=92)
    session = browser.open(f"http://127.0.0.1:{server.port}/", width=620, height=960)
    browser.wait_console(session, lambda t: t == "LP3D_READY", timeout=60)
    root = browser.call("DOM.getDocument", session=session)["root"]["nodeId"]
    node = browser.call("DOM.querySelector", {"nodeId": root, "selector": "#file"}, session=session)
    browser.call(
        "DOM.setFileInputFiles", {"files": [str(astronaut_path)], "nodeId": node["nodeId"]}, session=session
    )
    browser.wait_console(session, lambda t: t.startswith("LP3D_FINAL "), timeout=900)
    browser.click(session, "#live")
    browser.wait_console(
        session, lambda t: t.startswith("LP3D_LIVE ") and json.loads(t[10:])["frames"] >= 8, 300
    )
    browser.click(session, "#live")  # stop: the last frame's head climbs to the final quality
    browser.drag(session, browser.centre(session, "#view"), (-70.0, -25.0))  # turn it: 3D, not a photo
    finals = iter(range(1, 10**6))  # the first final image was the photo's: wait for the next one
    browser.wait_console(session, lambda t: t.startswith("LP3D_FINAL ") and next(finals) > 1, timeout=900)
    target.write_bytes(browser.screenshot(session))
    frames = [t for s, t in browser.console if s == session and t.startswith("LP3D_FRAME ")]
    print("page frames:", frames[-12:])
