"""Faces in photos: dlib's detector and five landmarks (lp3d.photo.faces), the camera and training
framing found from them (lp3d.photo.alignment), and the one-line refusals of photos without a usable
face (lp3d.photo.prepare)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lp3d.photo import (
    FACE_TEMPLATE,
    NoFaceError,
    PhotoError,
    align_face,
    face_descriptor,
    find_faces,
    prepare_photo,
)
from lp3d.photo.alignment import project_template
from lp3d.render.camera import look_at_camera
from support.paths import REPO


@pytest.fixture(scope="module")
def astronaut() -> np.ndarray:
    from skimage.data import astronaut

    return astronaut()


def test_the_astronaut_has_one_face_with_five_ordered_landmarks(astronaut) -> None:
    faces = find_faces(astronaut)
    assert len(faces) == 1
    lm = faces[0].landmarks
    assert lm.shape == (5, 2)
    # Image-right eye (outer, inner), image-left eye (outer, inner), nose base below the eyes.
    assert lm[0, 0] > lm[1, 0] > lm[3, 0] > lm[2, 0]
    assert lm[4, 1] > lm[:4, 1].max() and lm[3, 0] < lm[4, 0] < lm[1, 0]
    x, y, w, h = faces[0].box
    assert (lm[:, 0] > x).all() and (lm[:, 0] < x + w).all() and (lm[:, 1] > y).all()


def test_the_largest_of_several_faces_is_used(astronaut) -> None:
    from PIL import Image

    small = np.asarray(Image.fromarray(astronaut).resize((256, 256)))
    two = np.concatenate([astronaut, np.pad(small, ((0, 256), (0, 0), (0, 0)))], axis=1)
    prep = prepare_photo(two, 128, detect=True, name="two.png")
    assert "2 faces (the largest used)" in prep.description
    assert prep.detection is not None and prep.detection.face.box[0] < 512


def test_photos_without_a_usable_face_get_one_line(astronaut) -> None:
    from PIL import Image

    noise = np.random.default_rng(0).integers(0, 255, (300, 300, 3), dtype=np.uint8)
    with pytest.raises(NoFaceError, match=r"noise.png: no face found.*--no-detect") as e:
        prepare_photo(noise, 128, detect=True, name="noise.png")
    assert "\n" not in str(e.value)
    # A face a few pixels wide in a large image: found only with upsampling, refused as too small.
    tiny = np.full((900, 900, 3), 128, np.uint8)
    tiny[400:448, 400:448] = np.asarray(Image.fromarray(astronaut[60:260, 130:330]).resize((48, 48)))
    with pytest.raises(PhotoError, match="no face found|too small"):
        prepare_photo(tiny, 128, detect=True, name="tiny.png")


def test_align_face_recovers_the_camera_of_exact_landmarks() -> None:
    for yaw, pitch in ((0.0, 0.0), (20.0, 5.0), (-35.0, -10.0), (45.0, 20.0)):
        q = project_template(np.array([yaw]), np.array([pitch]), FACE_TEMPLATE)[0]
        # Seen in a photo: scaled to 300 px, turned 10° on screen, shifted.
        a = np.radians(10.0)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        pts = (q - 0.5) @ rot.T * 300.0 + [200.0, 180.0]
        found = align_face(pts, prior=False)
        assert found.yaw_deg == pytest.approx(yaw, abs=0.15) and found.pitch_deg == pytest.approx(
            pitch, abs=0.15
        )
        assert found.roll_deg == pytest.approx(10.0, abs=0.5) and found.residual < 1e-3
        # The crop undoes the similarity: the landmarks land where the template projects.
        m = found.crop.matrix(512)
        np.testing.assert_allclose(pts @ m[:, :2].T + m[:, 2], q * 512 - 0.5, atol=0.5)
        # The prior pulls a noisy estimate toward the frontal pose, never past it.
        pulled = align_face(pts)
        assert abs(pulled.yaw_deg) <= abs(yaw) + 0.1 and abs(pulled.pitch_deg) <= abs(pitch) + 0.1


def test_teacher_heads_at_known_cameras_are_framed_as_in_training() -> None:
    """A teacher head rendered at a camera off the training framing (rolled, zoomed, shifted) is put
    back: after alignment its landmarks sit within 16 px (of a 512² crop; bench/face_pose.py measures
    the spread over many heads) of where they sit in its render at the plain look-at camera."""
    import lp3d_render
    from lp3d.images import rgb_to_uint8
    from lp3d.render.camera import fov_to_focal
    from lp3d.render.native import native_triplane
    from lp3d.teachers.procedural import ProceduralTeacher

    r = 256
    tri = native_triplane(ProceduralTeacher(version=2).sample(1_000_000))
    plain = look_at_camera(yaw_deg=10.0, pitch_deg=5.0)
    moved = look_at_camera(
        yaw_deg=10.0, pitch_deg=5.0, roll_deg=6.0, focal=fov_to_focal(17.0), cx=0.53, cy=0.48
    )
    out = lp3d_render.render(tri, np.stack([plain, moved]), resolution=r, outputs=["rgb"])
    ref, img = (rgb_to_uint8(x) for x in out["rgb"])
    ref_faces, faces = find_faces(ref), find_faces(img)
    assert len(ref_faces) == 1 and len(faces) == 1
    found = align_face(faces[0].landmarks)
    m = found.crop.matrix(r)
    aligned = faces[0].landmarks @ m[:, :2].T + m[:, 2]
    err = np.linalg.norm(aligned - ref_faces[0].landmarks, axis=1).mean() * 512 / r
    assert err < 16.0, err
    # The camera's roll turns the content counter-clockwise: the face's tilt in the image is negative.
    assert found.roll_deg == pytest.approx(-6.0, abs=2.5)


def test_descriptors_tell_people_apart(astronaut) -> None:

    from PIL import Image

    face = find_faces(astronaut)[0]
    d = face_descriptor(astronaut, face)
    assert d.shape == (128,) and np.isfinite(d).all()
    # The same photo, smaller: the same person (well under dlib's 0.6).
    half = np.asarray(Image.fromarray(astronaut).resize((384, 384)))
    assert np.linalg.norm(face_descriptor(half, find_faces(half)[0]) - d) < 0.3
    other = REPO.parent / "shared" / "photos" / "obama.jpg"
    if other.exists():  # a second person, where the development photos are at hand
        rgb = np.asarray(Image.open(other).convert("RGB"))
        assert np.linalg.norm(face_descriptor(rgb, find_faces(rgb)[0]) - d) > 0.6


def test_missing_models_are_one_clear_line(monkeypatch) -> None:
    import importlib.util

    from lp3d.photo import faces

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "face_recognition_models" else real(n, *a)
    )
    with pytest.raises(PhotoError, match="pip install face_recognition_models"):
        faces.face_model_path("landmarks")


def test_the_mirrored_camera_is_the_mirrored_look_at() -> None:
    from lp3d.lift.pose import mirrored_camera

    for yaw, pitch in ((23.0, 7.0), (-40.0, -12.0)):
        cam = torch.from_numpy(look_at_camera(yaw_deg=yaw, pitch_deg=pitch, cx=0.46))
        np.testing.assert_allclose(
            mirrored_camera(cam).numpy(), look_at_camera(yaw_deg=-yaw, pitch_deg=pitch, cx=0.54), atol=1e-12
        )
