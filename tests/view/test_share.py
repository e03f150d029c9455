"""``lp3d share``: the page embeds the renderer's own WGSL (checked against ``crates/renderer/shaders/``),
is self-contained and small, keeps hostile text as data, refuses bad files like every reader, and, in a
real browser (headless Chromium, WebGPU on its SwiftShader CPU adapter), renders what ``lp3d_render``
renders: the test mode's image matches within 1e-3.

The browser tests need Debian's ``chromium`` (``scripts/install-system-deps.sh``); without it, or without
a WebGPU adapter in it, they fail with the reason. ``LP3D_SHARE_SCREENSHOT=docs/share.png`` also writes
the normal-mode screenshot there (how ``docs/share.png`` was made).
"""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

import lp3d_render
from lp3d.cli import main
from lp3d.errors import safe_text
from lp3d.render.camera import look_at_camera
from lp3d.render.triplane_io import save_triplane
from lp3d.share import PROBE_PREFIX, PROBE_SETTINGS, page_data, shader_stages
from lp3d.teachers.procedural import ProceduralTeacher
from support.browser import BrowserError, Chromium
from support.paths import REPO
from support.triplane_files import changed, good_arrays

SHADERS = REPO / "crates" / "renderer" / "shaders"
#: The issue's budget for a 64² head's page.
MAX_PAGE_BYTES_64 = 3_000_000
#: The browser's image against lp3d_render's, RGB in [-1, 1].
MAX_PROBE_ERROR = 1e-3
#: The view the probe renders (yaw, pitch in degrees).
PROBE_VIEW = (30.0, -10.0)


def _head(size: int = 64):
    """A procedural teacher head with float16 planes (the page's and the file's values agree)."""
    tri = ProceduralTeacher(resolution=size).sample(1_000_000)
    return dataclasses.replace(tri, planes=tri.planes.astype(np.float16))


def _data_block(page: str) -> dict:
    found = re.search(r'<script type="application/json" id="lp3d-data">(.*?)</script>', page, re.S)
    assert found is not None
    return json.loads(found.group(1))


#: The test page's final quality: small, because SwiftShader (WebGPU on the CPU) takes ~25 s for a
#: 64² · 48+48 frame on a loaded 2-core machine, and ~100 s for the default 128² · 48+48.
TEST_PAGE_ARGS = ["--resolution", "64", "--samples", "24+24"]
#: The screenshot's page (LP3D_SHARE_SCREENSHOT): the default quality, turned to show the head in 3D.
SCREENSHOT_PAGE_ARGS = ["--yaw", "25", "--pitch", "5"]


def _share(npz: Path, page: Path, *args: str, title: str = "procedural teacher head") -> Path:
    assert main(["share", str(npz), "-o", str(page), "--title", title, *args]) == 0
    return page


@pytest.fixture(scope="module")
def head_page(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """``(head.npz, head.html)``: a 64² teacher head and its page, written by ``lp3d share``."""
    folder = tmp_path_factory.mktemp("share")
    npz = folder / "head.npz"
    save_triplane(npz, _head())
    return npz, _share(npz, folder / "head.html", *TEST_PAGE_ARGS)


def test_the_page_embeds_the_renderers_wgsl_files(head_page) -> None:
    """One source of truth: the extension's shader_sources() are crates/renderer/shaders/*.wgsl, byte
    for byte, all of them, and the page carries exactly those, in the renderer's module order."""
    stages = shader_stages()
    assert sorted(name for name, _ in stages) == sorted(p.name for p in SHADERS.glob("*.wgsl"))
    for name, text in stages:
        assert text == (SHADERS / name).read_text(), f"{name}: lp3d_render is out of date (./dev setup)"
    assert list(lp3d_render.shader_sources().items()) == stages
    assert _data_block(head_page[1].read_text())["shaders"] == [list(s) for s in stages]


def test_the_page_is_self_contained_and_holds_the_triplane(head_page) -> None:
    npz, page = head_page
    text = page.read_text()
    assert page.stat().st_size <= MAX_PAGE_BYTES_64, page.stat().st_size
    assert "default-src 'none'" in text  # nothing is fetched at view time
    assert len(re.findall(r"<script", text, re.I)) == 2 and "src=" not in text
    data = _data_block(text)
    tri = _head()
    planes = np.frombuffer(base64.b64decode(data["planes"]["base64"]), "<f2")
    np.testing.assert_array_equal(planes.reshape(3, 64, 64, 32), tri.planes.transpose(0, 2, 3, 1))
    decoder = np.frombuffer(base64.b64decode(data["decoder"]["base64"]), "<f4")
    np.testing.assert_array_equal(decoder[: 64 * 32], tri.w0.ravel())
    np.testing.assert_array_equal(decoder[-36:-3], tri.b1)
    assert data["bounds"] == {"box_warp": 1.0, "ray_start": 2.25, "ray_end": 3.3}
    assert data["probe"]["resolution"] == PROBE_SETTINGS.resolution == 64


def test_hostile_text_stays_data(tmp_path: Path) -> None:
    """Text from the file (its source) and the title never become markup or code."""
    evil = "</script><script>alert(1)</script><!-- &amp; \u2028 <SCRIPT>"
    tri = dataclasses.replace(_head(16), source=evil)
    npz, page = tmp_path / "evil.npz", tmp_path / "evil.html"
    save_triplane(npz, tri)
    assert main(["share", str(npz), "-o", str(page), "--title", evil]) == 0
    text = page.read_text()
    assert len(re.findall(r"<script", text, re.I)) == 2
    assert len(re.findall(r"</script", text, re.I)) == 2
    data = _data_block(text)
    # As every string from a file: kept as text, with control and bidi characters escaped.
    assert data["source"] == safe_text(evil) and data["title"] == safe_text(evil)
    assert "<title>&lt;/script&gt;" in text


def test_share_refuses_bad_files_and_never_replaces_its_input(tmp_path: Path, capsys) -> None:
    cases = {
        "nan.npz": (changed(planes=np.full((3, 32, 6, 7), np.nan, np.float32)), "contains NaN/Inf"),
        "junk.npz": (b"PK\x03\x04 not a zip", "junk.npz"),
        "overflow.npz": (changed(planes=np.full((3, 32, 6, 7), 3e38, np.float32)), "overflow float32"),
        "wide.npz": (changed(planes=np.full((3, 32, 6, 7), 1e5, np.float32)), "float16's range"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        out = tmp_path / f"{name}.html"
        assert main(["share", str(tmp_path / name), "-o", str(out), "--float16"]) == 1, name
        err = capsys.readouterr().err
        assert name in err and message in err, err
        assert not out.exists() and not list(tmp_path.glob(".*tmp*")), name
    # Float32 planes beyond float16's range are shared in the file's precision, the default.
    assert main(["share", str(tmp_path / "wide.npz"), "-o", str(tmp_path / "wide.html")]) == 0
    assert _data_block((tmp_path / "wide.html").read_text())["planes"]["dtype"] == "float32"
    # An output that is the input (here a hard link with a page's name) is refused before any work.
    npz = tmp_path / "good.npz"
    npz.write_bytes(before := changed(planes=good_arrays()["planes"]))
    os.link(npz, tmp_path / "good.html")
    assert main(["share", str(npz), "-o", str(tmp_path / "good.html")]) == 1
    assert "destroy the input" in capsys.readouterr().err
    assert npz.read_bytes() == before


def test_page_data_refuses_settings_it_cannot_render() -> None:
    from lp3d.render.settings import RenderSettings, Skips

    with pytest.raises(ValueError, match="exact"):
        page_data(_head(16), title="x", settings=RenderSettings(skips=Skips(transmittance_threshold=0.01)))
    with pytest.raises(ValueError, match="deterministic"):
        page_data(_head(16), title="x", settings=RenderSettings(deterministic=False))


# ------------------------------------------------------------------------------- in a real browser


@pytest.fixture(scope="module")
def browser():
    try:
        chromium = Chromium()
    except BrowserError as e:
        pytest.fail(str(e))
    with chromium:
        yield chromium


def test_browser_renders_what_lp3d_render_renders(browser, head_page) -> None:
    """The test mode's image (64², 48+48, exact) equals lp3d_render.render of the same file and camera."""
    npz, page = head_page
    yaw, pitch = PROBE_VIEW
    session = browser.open(f"{page.as_uri()}#probe={yaw:g},{pitch:g}")
    try:
        line = browser.wait_console(session, lambda t: t.startswith(PROBE_PREFIX), timeout=240)
    except BrowserError as e:
        pytest.fail(f"{e} (a WebGPU adapter is needed: chromium --enable-unsafe-webgpu uses SwiftShader)")
    image = np.frombuffer(base64.b64decode(line[len(PROBE_PREFIX) :]), "<f4").reshape(3, 64, 64)
    camera = look_at_camera(yaw_deg=yaw, pitch_deg=pitch)
    kwargs = PROBE_SETTINGS.native_kwargs()
    expected = lp3d_render.render(lp3d_render.Triplane.load(str(npz)), camera, outputs=["rgb"], **kwargs)
    error = np.abs(image - expected["rgb"]).max()
    print(f"browser probe at yaw {yaw:g}, pitch {pitch:g}: max abs error {error:.2e}")
    assert error <= MAX_PROBE_ERROR
    assert expected["rgb"].std() > 0.1  # a head, not an empty image


def test_browser_viewer_reaches_its_final_quality(
    browser, head_page, model_head_page, tmp_path: Path
) -> None:
    """Normal mode climbs the quality ladder to the final image; the screenshot shows the head (the
    canvas is 512 CSS pixels wide from x = 44, y = 73, in a 600 x 720 window)."""
    from PIL import Image

    if target := os.environ.get("LP3D_SHARE_SCREENSHOT"):
        return _screenshots(browser, model_head_page[0], tmp_path, Path(target))
    session = browser.open(head_page[1].as_uri())
    line = browser.wait_console(session, lambda t: t.startswith("LP3D_FINAL "), timeout=180)
    assert line.startswith("LP3D_FINAL 64² · 24+24"), line
    shot = tmp_path / "share.png"
    shot.write_bytes(browser.screenshot(session))
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.float32)
    assert pixels.shape == (720, 600, 3)
    canvas = pixels[80:580, 50:550]
    assert canvas.std(axis=(0, 1)).max() > 20, "the canvas is blank"
    # Drag to the right and scroll in: the final image is of a turned, zoomed view; Reset returns.
    centre = browser.centre(session, "#view")
    browser.drag(session, centre, (100.0, 0.0))
    browser.mouse(session, "mouseWheel", *centre, deltaX=0, deltaY=-200)
    view = _final_view(browser, session, lambda v: v["zoom"] > 1)
    assert view["yaw"] < -10 and view["pitch"] == 0 and view["zoom"] == pytest.approx(np.exp(0.5))
    browser.click(session, "#reset")
    assert _final_view(browser, session, lambda v: v["zoom"] == 1) == {**view, "yaw": 0, "zoom": 1}


def _screenshots(browser: Chromium, npz: Path, folder: Path, target: Path) -> None:
    """``LP3D_SHARE_SCREENSHOT=docs/share.png`` (how it was made): the pages of a shipped-model head
    at the default quality, turned to show it in 3D, without (left) and with (right) its network, at
    their final views, side by side."""
    from PIL import Image

    shots = []
    for name, extra in (("raw", ["--no-superres"]), ("superres", [])):
        page = _share(npz, folder / f"{name}.html", *SCREENSHOT_PAGE_ARGS, *extra, title=MODEL_HEAD_TITLE)
        session = browser.open(page.as_uri())
        line = browser.wait_console(session, lambda t: t.startswith("LP3D_FINAL "), timeout=900)
        print(name, line)
        shots.append(Image.open(__import__("io").BytesIO(browser.screenshot(session))).convert("RGB"))
    w, h = shots[0].size
    both = Image.new("RGB", (2 * w + 8, h), (22, 24, 28))
    for i, shot in enumerate(shots):
        both.paste(shot, (i * (w + 8), 0))
    both.save(target, optimize=True)


def _final_view(browser: Chromium, session: str, accept) -> dict:
    """The view of the next ``LP3D_FINAL`` line that ``accept`` takes (its rung's time left out)."""

    def view(line: str) -> dict:
        found = json.loads(line[line.index("{") :])
        return {k: found[k] for k in ("yaw", "pitch", "zoom")}

    line = browser.wait_console(session, lambda t: t.startswith("LP3D_FINAL ") and accept(view(t)), 180)
    return view(line)


#: The title of the pages of a head the shipped model lifted (from a seeded random image).
MODEL_HEAD_TITLE = "a head lifted by the shipped model"


@pytest.fixture(scope="module")
def model_head_page(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """``(head.npz, head.html, raw.html)``: a head the shipped model lifted, its page (which carries
    the model's super-resolution network) and its page without it (``--no-superres``)."""
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder

    folder = tmp_path_factory.mktemp("share-sr")
    encoder = load_encoder(DEFAULT_MODEL)
    image = np.random.default_rng(7).uniform(-1, 1, (1, 3, 128, 128)).astype(np.float32)
    npz = folder / "head.npz"
    save_triplane(npz, encoder.package.triplane(encoder.run(image)[0]))
    args = ["--resolution", "32", "--samples", "12+12"]
    raw = _share(npz, folder / "raw.html", *args, "--no-superres", title=MODEL_HEAD_TITLE)
    return npz, _share(npz, folder / "head.html", *args, title=MODEL_HEAD_TITLE), raw


def test_a_shipped_model_head_page_carries_its_network(model_head_page) -> None:
    """The page holds the renderer's plan of the network (its packed weights and dispatches), as
    ``lp3d_render.SuperRes.plan`` makes it; ``--no-superres`` leaves it out; a teacher head's page
    (another decoder) has none."""
    from lp3d.lift.gpu_superres import load_gpu_superres

    _, page, raw = model_head_page
    data = _data_block(page.read_text())["superres"]
    plan = load_gpu_superres().plan()
    weights = np.frombuffer(base64.b64decode(data.pop("weights_base64")), "<f4")
    np.testing.assert_array_equal(weights, plan.pop("weights"))
    assert data == {**plan, "weights_floats": weights.size}
    assert (data["input_resolution"], data["output_resolution"]) == (64, 256)
    assert _data_block(raw.read_text())["superres"] is None
    extra = page.stat().st_size - raw.stat().st_size
    print(f"the network adds {extra} bytes to the page")
    assert 0 < extra < 4 * weights.nbytes / 3 + 20_000  # base64 of the weights, the steps


def test_browser_super_resolves_what_lp3d_render_super_resolves(browser, model_head_page) -> None:
    """The test mode's network image (the page's samples, 64² features to 256²) equals
    ``lp3d_render.render(..., superres=)``'s; the viewer's final view is the network's image."""
    from lp3d.lift.gpu_superres import load_gpu_superres

    npz, page, _ = model_head_page
    yaw, pitch = PROBE_VIEW
    session = browser.open(f"{page.as_uri()}#probe={yaw:g},{pitch:g}&superres=1")
    line = browser.wait_console(session, lambda t: t.startswith(PROBE_PREFIX), timeout=240)
    image = np.frombuffer(base64.b64decode(line[len(PROBE_PREFIX) :]), "<f4").reshape(3, 256, 256)
    camera = look_at_camera(yaw_deg=yaw, pitch_deg=pitch)
    tri = lp3d_render.Triplane.load(str(npz))
    kwargs = {"resolution": 64, "depth_resolution": 12, "depth_resolution_importance": 12}
    expected = lp3d_render.render(tri, camera, outputs=["depth"], superres=load_gpu_superres(), **kwargs)
    error = np.abs(image - expected["image"]).max()
    print(f"browser super-resolution at yaw {yaw:g}, pitch {pitch:g}: max abs error {error:.2e}")
    assert error <= MAX_PROBE_ERROR
    assert expected["image"].std() > 0.1

    session = browser.open(page.as_uri())
    line = browser.wait_console(session, lambda t: t.startswith("LP3D_FINAL "), timeout=240)
    final = json.loads(line[line.index("{") :])
    assert line.startswith("LP3D_FINAL 32² · 12+12") and final["superres"] is True, line
    print(f"the page's still view: exact {final['exact_ms']:.0f} ms, super-resolved {final['ms']:.0f} ms")


def test_browser_says_when_webgpu_is_missing(browser, head_page) -> None:
    """A browser without WebGPU (navigator.gpu removed before the page runs) gets a message, not a
    blank page."""
    session = browser.open(head_page[1].as_uri(), before="delete Navigator.prototype.gpu;")
    with pytest.raises(BrowserError, match="needs WebGPU.*navigator.gpu is missing"):
        browser.wait_console(session, lambda t: False, timeout=60)
