"""Fixtures of the command-line tests: a sample triplane, a tiny model package with its checkpoints,
test photos (a face and assorted bad files) and corrupt triplane files. The data fixtures are made
once per session: no test changes them."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane
from support.cli import SPHERE_RADIUS
from support.tiny_model import tiny_onnx_package


@pytest.fixture(scope="session")
def sphere(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small sample triplane (a coloured sphere of radius 0.3) as a .npz file."""
    path = tmp_path_factory.mktemp("scene") / "sphere.npz"
    save_triplane(path, coloured_sphere(size=32, radius=SPHERE_RADIUS))
    return path


@pytest.fixture(scope="session")
def model(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A randomly initialised ``tiny`` encoder: ONNX + sidecar, an export-style checkpoint and a
    training-style checkpoint, all with the sphere's decoder."""
    import torch

    folder = tmp_path_factory.mktemp("model")
    onnx_path, enc, tri, bounds = tiny_onnx_package(folder)
    decoder = {k: torch.from_numpy(getattr(tri, k)) for k in ("w0", "b0", "w1", "b1")}
    plain = folder / "tiny.pt"
    torch.save(
        {"config": enc.config.to_dict(), "encoder": enc.state_dict(), "decoder": decoder, "bounds": bounds},
        plain,
    )
    # The layout python -m lp3d.train writes: JSON configs, one 'student' state dict with prefixes.
    student = {f"encoder.{k}": v for k, v in enc.state_dict().items()}
    student.update({f"decoder.{k}": v for k, v in decoder.items()})
    train = folder / "step-000010.pt"
    torch.save(
        {
            "format": "lp3d-train-checkpoint-v1",
            "config": json.dumps({"encoder": enc.config.to_dict()}),
            "scene": json.dumps(bounds),
            "student": student,
        },
        train,
    )
    return {"onnx": onnx_path, "pt": plain, "train": train, "folder": folder}


@pytest.fixture(scope="session")
def photos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Test photos: a face (skimage's astronaut), a face-free image and assorted bad files."""
    from skimage.data import astronaut

    folder = tmp_path_factory.mktemp("photos")
    face = astronaut()
    out = {"face": folder / "face.jpg", "face_crop": folder / "face_crop.png"}
    Image.fromarray(face).save(out["face"], quality=92)
    Image.fromarray(face[:300, 80:380]).save(out["face_crop"])
    rng = np.random.default_rng(0)
    out["noface"] = folder / "noface.png"
    Image.fromarray(np.broadcast_to(np.linspace(40, 200, 256, dtype=np.uint8), (256, 256))).convert(
        "RGB"
    ).save(out["noface"])
    out["grey"] = folder / "grey.png"
    Image.fromarray(face[:300, 80:380].mean(axis=2).astype(np.uint8)).save(out["grey"])
    out["rgba"] = folder / "rgba.png"
    rgba = np.concatenate([face[:300, 80:380], np.full((300, 300, 1), 200, np.uint8)], axis=2)
    Image.fromarray(rgba, "RGBA").save(out["rgba"])
    out["text"] = folder / "notes.jpg"
    out["text"].write_text("this is not an image\n")
    out["empty"] = folder / "empty.png"
    out["empty"].write_bytes(b"")
    out["truncated"] = folder / "truncated.jpg"
    out["truncated"].write_bytes(out["face"].read_bytes()[:2000])
    out["noise"] = folder / "noise.png"
    Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(out["noise"])
    # A PNG whose header claims 12000 x 12000 pixels (144 MP): rejected before any pixel is decoded.
    out["huge"] = folder / "huge.png"
    ihdr = struct.pack(">IIBBBBB", 12000, 12000, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    out["huge"].write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", 13)
        + chunk
        + struct.pack(">I", zlib.crc32(chunk))
        + struct.pack(">I", 0)
        + b"IEND"
        + struct.pack(">I", zlib.crc32(b"IEND"))
    )
    return out


@pytest.fixture()
def bad_npz(tmp_path: Path, sphere: Path) -> dict[str, Path]:
    """A corrupt (random bytes), a truncated and an empty .npz."""
    out = {
        "garbage": tmp_path / "garbage.npz",
        "truncated": tmp_path / "truncated.npz",
        "empty": tmp_path / "e.npz",
    }
    out["garbage"].write_bytes(np.random.default_rng(1).integers(0, 255, 4000, dtype=np.uint8).tobytes())
    out["truncated"].write_bytes(sphere.read_bytes()[:3000])
    out["empty"].write_bytes(b"")
    return out
