"""EG3D teacher adapter, tested on a tiny stand-in generator with EG3D's interface (no real pickle here)."""

from __future__ import annotations

import copy
import pickle
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

import lp3d.teachers.eg3d as eg3d_mod
import lp3d.teachers.eg3d_loading
from lp3d.render.camera import look_at_camera
from lp3d.render.triplane import TriplaneData
from lp3d.teachers import Teacher
from lp3d.teachers.eg3d import EG3D_HINT, EG3DLoadError, EG3DTeacher, load_eg3d_generator
from support.eg3d_standin import NUM_WS, PLANE_RES, W_DIM, Z_DIM, StandInGenerator


def make_teacher(gen: StandInGenerator | None = None, **kwargs: object) -> EG3DTeacher:
    return EG3DTeacher(gen if gen is not None else StandInGenerator(), **kwargs)  # type: ignore[arg-type]


def decode_numpy(f: np.ndarray, w0: np.ndarray, b0: np.ndarray, w1: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """The decoder MLP with effective weights: softplus(w0 f + b0) -> w1 h + b1 (torch's softplus)."""
    a = f @ w0.T + b0
    h = np.where(a > 20, a, np.log1p(np.exp(np.minimum(a, 20))))
    return h @ w1.T + b1


# ------------------------------------------------------------------------------------------------
# Decoder


@pytest.mark.parametrize(
    ("lr_mul", "keep_lr_attr"),
    [(1.0, True), (1.0, False), (0.5, False), (2.0, True)],
    ids=["lr1", "lr1-eg3d-attrs", "lr0.5-eg3d-attrs", "lr2"],
)
def test_effective_decoder_reproduces_the_generators_decoder(lr_mul: float, keep_lr_attr: bool) -> None:
    gen = StandInGenerator(decoder_lr_mul=lr_mul, keep_lr_attr=keep_lr_attr)
    w0, b0, w1, b1 = make_teacher(gen).decoder()
    assert [a.shape for a in (w0, b0, w1, b1)] == [(64, 32), (64,), (33, 64), (33,)]
    assert all(a.dtype == np.float32 for a in (w0, b0, w1, b1))
    net = gen.decoder.net
    # The effective weights are what the layer's own forward multiplies with, bit for bit.
    with torch.no_grad():
        assert np.array_equal(w0, (net[0].weight * net[0].weight_gain).numpy())
        assert np.array_equal(w1, (net[2].weight * net[2].weight_gain).numpy())
        assert np.array_equal(b1, (net[2].bias * net[2].bias_gain).numpy())
    f = np.random.default_rng(0).standard_normal((512, 32)).astype(np.float32)
    # Same arithmetic in float64 (no float32 summation-order noise): equal to 1e-6.
    with torch.no_grad():
        expected64 = copy.deepcopy(net).double()(torch.from_numpy(f).double()).numpy()
    got64 = decode_numpy(f.astype(np.float64), *(a.astype(np.float64) for a in (w0, b0, w1, b1)))
    np.testing.assert_allclose(got64, expected64, rtol=0, atol=1e-6)
    # And against the decoder's own float32 forward, to float32 rounding (outputs reach ~3).
    with torch.no_grad():
        expected32 = net(torch.from_numpy(f)).numpy()
    np.testing.assert_allclose(decode_numpy(f, w0, b0, w1, b1), expected32, rtol=1e-6, atol=1e-6)


def test_decoder_returns_copies() -> None:
    teacher = make_teacher()
    teacher.decoder()[0][:] = 0.0
    assert np.any(teacher.decoder()[0] != 0.0)


def test_decoder_that_is_not_eg3ds_is_refused() -> None:
    gen = StandInGenerator()
    gen.decoder.net[1] = torch.nn.Softplus(beta=2)
    with pytest.raises(ValueError, match="Softplus"):
        make_teacher(gen)
    gen = StandInGenerator()
    gen.decoder.net[0].weight_gain = 1.0  # inconsistent with lr_multiplier / sqrt(32)
    with pytest.raises(ValueError, match="weight_gain"):
        make_teacher(gen)


# ------------------------------------------------------------------------------------------------
# Sampling


def test_sample_fields_shapes_and_protocol() -> None:
    teacher = make_teacher()
    assert isinstance(teacher, Teacher)
    tri = teacher.sample(3)
    assert isinstance(tri, TriplaneData)
    assert tri.planes.shape == (3, 32, PLANE_RES, PLANE_RES) and tri.planes.dtype == np.float32
    assert tri.source == "eg3d seed 3"
    assert (tri.box_warp, tri.ray_start, tri.ray_end) == (1.0, 2.25, 3.3)
    for got, want in zip((tri.w0, tri.b0, tri.w1, tri.b1), teacher.decoder(), strict=True):
        assert np.array_equal(got, want)


def test_rendering_kwargs_become_triplane_fields_and_settings() -> None:
    rk = dict(box_warp=1.6, ray_start=0.1, ray_end=2.6, depth_resolution=64, depth_resolution_importance=32)
    teacher = make_teacher(StandInGenerator(rendering_kwargs=rk))
    tri = teacher.sample(0)
    assert (tri.box_warp, tri.ray_start, tri.ray_end) == (1.6, 0.1, 2.6)
    s = teacher.render_settings()
    assert (s.resolution, s.depth_resolution, s.depth_resolution_importance, s.white_back) == (
        128,
        64,
        32,
        False,
    )
    assert teacher.render_settings(resolution=64).resolution == 64


@pytest.mark.parametrize(
    ("rk", "match"),
    [
        (dict(ray_start="auto", ray_end="auto"), "auto"),
        (dict(clamp_mode="relu"), "clamp_mode"),
        (dict(disparity_space_sampling=True), "disparity"),
    ],
)
def test_rendering_kwargs_lp3d_cannot_render_are_refused(rk: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make_teacher(StandInGenerator(rendering_kwargs=rk))


def test_planes_are_the_backbone_output_split_like_eg3d() -> None:
    gen = StandInGenerator()
    teacher = make_teacher(gen)
    planes = teacher.planes([4]).numpy()
    with torch.no_grad():
        raw = gen.backbone.synthesis(gen.backbone.synthesis.calls[-1]["ws"], noise_mode="const").numpy()
    for p in range(3):
        for k in (0, 17, 31):
            assert np.array_equal(planes[0, p, k], raw[0, 32 * p + k])


def test_sample_is_deterministic_per_seed() -> None:
    gen = StandInGenerator()
    a, b = make_teacher(gen), make_teacher(gen)
    assert np.array_equal(a.sample(5).planes, a.sample(5).planes)
    assert np.array_equal(a.sample(5).planes, b.sample(5).planes)
    assert not np.allclose(a.sample(5).planes, a.sample(6).planes)
    # Const noise (seeded "random" noise would make the planes depend on torch's global RNG).
    assert gen.backbone.synthesis.calls[-1]["noise_mode"] == "const"
    assert gen.backbone.synthesis.calls[-1]["update_emas"] is False


def test_z_is_drawn_like_eg3d_gen_samples() -> None:
    gen = StandInGenerator()
    make_teacher(gen).sample(1234)
    z = gen.backbone.mapping.calls[-1]["z"]
    assert z.shape == (1, Z_DIM) and z.dtype == torch.float32
    expected = np.random.RandomState(1234).randn(1, Z_DIM).astype(np.float32)
    assert np.array_equal(z.numpy(), expected)


@pytest.mark.parametrize("seed", [-1, 2**32, 1.5, True])
def test_bad_seeds_are_refused(seed: object) -> None:
    with pytest.raises(ValueError, match="seed"):
        make_teacher().sample(seed)  # type: ignore[arg-type]


def test_sample_batch_matches_sample() -> None:
    teacher = make_teacher(max_batch=2)
    seeds = [7, 1, 7, 30]
    batch = teacher.sample_batch(seeds)
    assert [t.source for t in batch] == [f"eg3d seed {s}" for s in seeds]
    # Equal up to float32 summation order: a batch of 2 and a batch of 1 go through different BLAS
    # kernels (gemm vs gemv), which sum in another order. torch 2.15 on an AVX-512 CPU differs by
    # 1.0e-6 on a value of 0.87 (about 10 float32 ulps), so the bound is relative as well.
    for s, tri in zip(seeds, batch, strict=True):
        np.testing.assert_allclose(tri.planes, teacher.sample(s).planes, rtol=2e-6, atol=1e-6)
    assert teacher.sample_batch([]) == []


# ------------------------------------------------------------------------------------------------
# Mapping: truncation and pose conditioning


def test_truncation_is_applied() -> None:
    gen = StandInGenerator()
    w = make_teacher(gen, truncation_psi=1.0).latents([9])
    assert gen.backbone.mapping.calls[-1]["psi"] == 1.0
    teacher = make_teacher(gen)  # defaults: psi 0.7, cutoff 14
    ws = teacher.latents([9])
    call = gen.backbone.mapping.calls[-1]
    assert (call["psi"], call["cutoff"]) == (0.7, 14)
    assert ws.shape == (1, NUM_WS, W_DIM)
    w_avg = gen.backbone.mapping.w_avg
    torch.testing.assert_close(ws, w_avg + 0.7 * (w - w_avg), rtol=0, atol=1e-6)
    # psi = 0 collapses every identity onto the average w; the cutoff limits which ws are truncated.
    ws0 = make_teacher(gen, truncation_psi=0.0).latents([1, 2])
    torch.testing.assert_close(ws0, w_avg.expand_as(ws0), rtol=0, atol=0)
    ws_cut = make_teacher(gen, truncation_psi=0.0, truncation_cutoff=2).latents([9])
    torch.testing.assert_close(ws_cut[:, :2], w_avg.expand(1, 2, W_DIM), rtol=0, atol=0)
    torch.testing.assert_close(ws_cut[:, 2:], w[:, 2:], rtol=0, atol=0)


#: gen_videos.py's LookAtPoseSampler.sample(3.14/2, 3.14/2, ...) as look_at_camera angles: yaw is
#: h - pi/2 and pitch asin(1 - 2v/pi) (lp3d.render.camera.eg3d_angles), so 3.14 for pi puts the camera
#: 0.0456° toward -x and 0.0290° up.
GEN_VIDEOS_YAW_DEG = float(np.degrees((3.14 - np.pi) / 2))
GEN_VIDEOS_PITCH_DEG = float(np.degrees(np.arcsin(1.0 - 3.14 / np.pi)))


def test_mapping_is_conditioned_on_gen_videos_camera_at_the_pivot() -> None:
    assert GEN_VIDEOS_YAW_DEG == pytest.approx(-0.04563, abs=1e-5)
    assert GEN_VIDEOS_PITCH_DEG == pytest.approx(0.02905, abs=1e-5)
    gen = StandInGenerator()
    make_teacher(gen).sample(0)
    c = gen.backbone.mapping.calls[-1]["c"].numpy()
    # radius 2.7, looking at (0, 0, 0.2), focal 4.2647, from gen_videos.py's angles
    expected = look_at_camera(yaw_deg=GEN_VIDEOS_YAW_DEG, pitch_deg=GEN_VIDEOS_PITCH_DEG)
    np.testing.assert_allclose(c, expected[None].astype(np.float32), rtol=0, atol=1e-6)
    # The centre: 2.7 from the origin, a little toward -x and up; not the exactly frontal camera.
    centre = expected[[3, 7, 11]]
    assert np.linalg.norm(centre) == pytest.approx(2.7, abs=1e-12)
    assert centre[0] < -1e-3 and centre[1] > 1e-3
    assert np.abs(c - look_at_camera()[None]).max() > 1e-4
    # AFHQ-style pivot from rendering_kwargs; an explicit pose wins over both.
    gen = StandInGenerator(rendering_kwargs=dict(avg_camera_pivot=[0, 0, -0.06]))
    make_teacher(gen).sample(0)
    expected = look_at_camera(
        yaw_deg=GEN_VIDEOS_YAW_DEG, pitch_deg=GEN_VIDEOS_PITCH_DEG, lookat=(0.0, 0.0, -0.06)
    )
    np.testing.assert_allclose(
        gen.backbone.mapping.calls[-1]["c"].numpy(), expected[None].astype(np.float32), rtol=0, atol=1e-6
    )
    pose = look_at_camera(yaw_deg=20.0)
    make_teacher(gen, conditioning_pose=pose).sample(0)
    assert np.array_equal(gen.backbone.mapping.calls[-1]["c"].numpy(), pose[None].astype(np.float32))


def test_conditioning_camera_follows_the_chosen_eg3d_script() -> None:
    """gen_videos.py conditions with focal 4.2647; gen_samples.py derives 4.26339 from its 18.837° field
    of view with EG3D's rounded constants, and uses the exactly frontal camera."""
    from lp3d.teachers.eg3d import CONDITIONING_FOCALS

    assert CONDITIONING_FOCALS["gen_videos"] == 4.2647
    assert CONDITIONING_FOCALS["gen_samples"] == pytest.approx(4.263391, abs=1e-6)
    for script, focal in CONDITIONING_FOCALS.items():
        gen = StandInGenerator()
        make_teacher(gen, conditioning=script).sample(0)
        c = gen.backbone.mapping.calls[-1]["c"].numpy()[0]
        assert c[16] == c[20] == np.float32(focal)  # fx, fy of the normalised intrinsics
    # gen_samples.py conditions on the exactly frontal camera (np.pi/2, not 3.14/2).
    gen = StandInGenerator()
    make_teacher(gen, conditioning="gen_samples").sample(0)
    frontal = look_at_camera(focal=CONDITIONING_FOCALS["gen_samples"])
    assert np.array_equal(gen.backbone.mapping.calls[-1]["c"].numpy(), frontal[None].astype(np.float32))
    with pytest.raises(ValueError, match="conditioning must be one of"):
        make_teacher(StandInGenerator(), conditioning="gen_images")


def test_unconditional_generator_gets_an_empty_label() -> None:
    gen = StandInGenerator(c_dim=0)
    make_teacher(gen).sample(0)
    assert gen.backbone.mapping.calls[-1]["c"].shape == (1, 0)


# ------------------------------------------------------------------------------------------------
# Super-resolution with a constant w


def test_superresolve_uses_a_constant_w_of_ones() -> None:
    gen = StandInGenerator()
    teacher = make_teacher(gen)
    feat = torch.randn(2, 32, 128, 128, generator=torch.Generator().manual_seed(0))
    img = teacher.superresolve(feat)
    assert img.shape == (2, 3, 512, 512) and img.dtype == torch.float32
    call = gen.superresolution.calls[-1]
    assert call["noise_mode"] == "none"
    assert torch.equal(call["rgb"], feat[:, :3]) and torch.equal(call["x"], feat)
    assert call["ws"].shape == (2, NUM_WS, W_DIM)
    assert torch.equal(call["ws"], torch.ones(2, NUM_WS, W_DIM))
    # Constant: the same feature image gives the same image whatever identity was sampled before.
    teacher.sample(11)
    assert torch.equal(teacher.superresolve(feat.numpy()), img)


def test_superresolve_mean_and_explicit_w() -> None:
    gen = StandInGenerator()
    make_teacher(gen, sr_w="mean").superresolve(torch.zeros(1, 32, 8, 8))
    ws = gen.superresolution.calls[-1]["ws"]
    assert torch.equal(ws, gen.backbone.mapping.w_avg.expand(1, NUM_WS, W_DIM))
    vec = np.linspace(-1.0, 1.0, W_DIM)
    make_teacher(gen, sr_w=vec).superresolve(torch.zeros(1, 32, 8, 8))
    assert np.allclose(gen.superresolution.calls[-1]["ws"][0, -1].numpy(), vec)
    with pytest.raises(ValueError, match="sr_w"):
        make_teacher(gen, sr_w=np.ones(W_DIM + 1)).superresolve(torch.zeros(1, 32, 8, 8))
    with pytest.raises(ValueError, match="feature_image"):
        make_teacher(gen).superresolve(torch.zeros(1, 3, 8, 8))


# ------------------------------------------------------------------------------------------------
# Interface checks


def test_generator_without_eg3d_interface_is_refused() -> None:
    gen = StandInGenerator()
    del gen.backbone.synthesis
    with pytest.raises(TypeError, match=r"backbone.synthesis"):
        make_teacher(gen)
    with pytest.raises(TypeError, match="z_dim"):
        EG3DTeacher(torch.nn.Module())


# ------------------------------------------------------------------------------------------------
# Loading pickles


@pytest.fixture
def clean_eg3d_modules() -> Iterator[None]:
    """Forget fake EG3D packages (``training`` ...) imported by a test, and restore sys.path."""
    path = list(sys.path)
    yield
    sys.path[:] = path
    for name in list(sys.modules):
        if name.split(".")[0] in eg3d_mod.EG3D_SOURCE_PACKAGES:
            del sys.modules[name]


def _forget_fake_packages() -> None:
    for name in list(sys.modules):
        if name.split(".")[0] in eg3d_mod.EG3D_SOURCE_PACKAGES:
            del sys.modules[name]


def fake_eg3d_source(root: Path, *, extra: dict[str, str] | None = None) -> Path:
    """A directory shaped like NVlabs/eg3d/eg3d: empty torch_utils/, dnnlib/, training/ packages."""
    for pkg in eg3d_mod.EG3D_SOURCE_PACKAGES:
        (root / pkg).mkdir(parents=True)
        (root / pkg / "__init__.py").write_text("")
    for rel, text in (extra or {}).items():
        (root / rel).write_text(text)
    return root


def dump(path: Path, obj: object) -> Path:
    with open(path, "wb") as f:
        pickle.dump(obj, f)
    return path


def test_missing_pickle_says_what_to_pass(tmp_path: Path) -> None:
    for path in (None, tmp_path / "ffhq.pkl"):
        with pytest.raises(EG3DLoadError) as e:
            EG3DTeacher.from_pickle(path, eg3d_source=fake_eg3d_source(tmp_path / f"src{path is None}"))
        msg = str(e.value)
        assert EG3D_HINT in msg
        # The flags the hint names are the ones lp3d train and lp3d eval really have.
        assert "--teacher-pkl" in msg and "--eg3d-source" in msg and "ffhqrebalanced512-128.pkl" in msg
        assert "--eg3d-pkl" not in msg
        if path is not None:
            assert str(path) in msg


def test_missing_source_says_what_to_pass(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pkl = dump(tmp_path / "g.pkl", {"G_ema": 0})
    with pytest.raises(EG3DLoadError, match="source directory not found") as e:
        load_eg3d_generator(pkl, eg3d_source=tmp_path / "nope")
    assert EG3D_HINT in str(e.value)
    (tmp_path / "empty" / "torch_utils").mkdir(parents=True)
    with pytest.raises(EG3DLoadError, match=r"missing dnnlib/, training/") as e:
        load_eg3d_generator(pkl, eg3d_source=tmp_path / "empty")
    assert "--eg3d-source" in str(e.value)
    monkeypatch.setattr(lp3d.teachers.eg3d_loading, "_eg3d_source_importable", lambda: False)
    with pytest.raises(EG3DLoadError, match="not importable") as e:
        load_eg3d_generator(pkl)
    assert EG3D_HINT in str(e.value)


def test_not_an_eg3d_pickle(tmp_path: Path) -> None:
    src = fake_eg3d_source(tmp_path / "src")
    for name, obj, match in [
        ("list.pkl", [1, 2], "got list"),
        ("dict.pkl", {"G": 1, "D": 2}, r"got a dict with keys \['D', 'G'\]"),
    ]:
        with pytest.raises(EG3DLoadError, match=match) as e:
            load_eg3d_generator(dump(tmp_path / name, obj), eg3d_source=src)
        assert "'G_ema'" in str(e.value) and EG3D_HINT in str(e.value)
    (tmp_path / "text.pkl").write_text("not a pickle")
    with pytest.raises(EG3DLoadError, match="could not unpickle"):
        load_eg3d_generator(tmp_path / "text.pkl", eg3d_source=src)


@pytest.mark.usefixtures("clean_eg3d_modules")
def test_from_pickle_loads_g_ema_with_the_source_on_sys_path_for_unpickling_only(tmp_path: Path) -> None:
    # The pickle's class lives in the (fake) source tree, so it unpickles only with that tree on the path.
    src = fake_eg3d_source(
        tmp_path / "repo" / "eg3d",
        extra={"training/tiny_net.py": "class TinyNet:\n    answer = 42\n"},
    )
    sys.path.insert(0, str(src))
    import training.tiny_net  # type: ignore[import-not-found]

    pkl = dump(tmp_path / "tiny.pkl", {"G": 0, "D": 0, "G_ema": training.tiny_net.TinyNet()})
    sys.path.remove(str(src))
    _forget_fake_packages()

    loaded = load_eg3d_generator(pkl, eg3d_source=tmp_path / "repo")  # the repository root works too
    assert type(loaded).__name__ == "TinyNet" and loaded.answer == 42
    assert str(src) not in sys.path
    # A pickle of something else (a 2D StyleGAN2 generator, say) is a load error, not a traceback.
    with pytest.raises(EG3DLoadError, match="TriPlaneGenerator interface.*not a 2D StyleGAN") as e:
        EG3DTeacher.from_pickle(pkl, eg3d_source=src)
    assert str(pkl) in str(e.value)
    _forget_fake_packages()

    # Without the source tree: ModuleNotFoundError becomes a message naming --eg3d-source.
    other = fake_eg3d_source(tmp_path / "other")
    with pytest.raises(EG3DLoadError, match=r"'training.tiny_net' from EG3D's source tree") as e:
        load_eg3d_generator(pkl, eg3d_source=other)
    assert str(other) in str(e.value) and "--eg3d-source" in str(e.value)
    # ... and a `training` imported from elsewhere is not silently used.
    with pytest.raises(EG3DLoadError, match="shadow"):
        load_eg3d_generator(pkl, eg3d_source=src)


def test_from_pickle_builds_a_working_teacher(tmp_path: Path) -> None:
    gen = StandInGenerator(seed=3)
    pkl = dump(tmp_path / "standin.pkl", {"G": None, "D": None, "G_ema": gen})
    teacher = EG3DTeacher.from_pickle(pkl, eg3d_source=fake_eg3d_source(tmp_path / "src"), truncation_psi=0.5)
    assert teacher.truncation_psi == 0.5
    assert not teacher.generator.training
    assert not any(p.requires_grad for p in teacher.generator.parameters())
    assert np.array_equal(teacher.sample(2).planes, make_teacher(gen, truncation_psi=0.5).sample(2).planes)
    assert [a.tolist() for a in teacher.decoder()] == [a.tolist() for a in make_teacher(gen).decoder()]


@pytest.mark.usefixtures("clean_eg3d_modules")
def test_an_eg3d_run_resumes_and_evaluates_without_being_told_the_teacher_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run records the pickle and source paths (absolute) in its checkpoints; ``--resume`` and
    ``lp3d.evaluation`` rebuild the teacher from them, from another working directory too."""
    import json

    from lp3d.evaluation import EvalSettings
    from lp3d.evaluation import evaluate_checkpoint as eval_run
    from lp3d.train import main as train_main
    from lp3d.training import load_checkpoint

    pkl = dump(tmp_path / "standin.pkl", {"G": None, "D": None, "G_ema": StandInGenerator(seed=3)})
    src = fake_eg3d_source(tmp_path / "src")
    monkeypatch.chdir(tmp_path)
    out = Path("run")
    first = ["--config", "tiny-paper", "--teacher", "eg3d", "--teacher-pkl", "standin.pkl"]
    first += ["--eg3d-source", "src", "--eg3d-conditioning", "gen_samples", "--batch", "1"]
    assert train_main([*first, "--max-steps", "1", "--out", str(out), "--no-progress"]) == 0
    recorded = json.loads(load_checkpoint(out)["teacher_args"])
    assert recorded == {
        "teacher_pkl": str(pkl.resolve()),
        "eg3d_source": str(src.resolve()),
        "conditioning": "gen_samples",
    }
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    run = tmp_path / "run"
    assert train_main(["--resume", str(run), "--max-steps", "2", "--no-progress"]) == 0
    ckpt = load_checkpoint(run)
    assert ckpt["step"] == 2 and json.loads(ckpt["teacher_args"]) == recorded
    # A resumed run keeps its teacher: another conditioning is refused.
    assert train_main(["--resume", str(run), "--eg3d-conditioning", "gen_videos", "--no-progress"]) == 1
    settings = EvalSettings(n_identities=2, baseline_steps=0, timing_repeats=1)
    report_path, _, _ = eval_run(run, out=tmp_path / "eval", settings=settings)
    assert report_path.is_file()
