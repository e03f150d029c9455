"""Is a lifted photo still its person? Identity and pose on real photos, measured as the paper does
(``lp3d eval-photos``).

Each photo is lifted as ``lp3d encode`` lifts it (face found, aligned, encoded; refined when asked),
its head rendered (super-resolved by the package's network) at the novel-view yaws, and every view
compared with the photo by an independent face-recognition model, dlib's ResNet descriptors
(:func:`lp3d.photo.face_descriptor`): the distance (dlib calls two faces one person below
:data:`SAME_PERSON_DISTANCE`) and the cosine similarity of the descriptors. Also per view: whether a
face is found at all, and its pose error (the landmark camera of :mod:`lp3d.photo.alignment` on the
render against the yaw asked); per photo, the input view's PSNR, SSIM and ID distance on the face
region, and the face's depth relief (the spread of the rendered depth over the face region at the
photo's camera) of the final head and of the encoder's: a refine that flattens the head into a photo
on a card shows as a relief far below the encoder's.

May import :mod:`lp3d.photo`, :mod:`lp3d.lift`, :mod:`lp3d.render` and :mod:`lp3d.training` (SSIM).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lp3d.images import rgb_to_uint8
from lp3d.lift.inference import LoadedEncoder, LoadedSuperres
from lp3d.lift.refine_settings import RefineSettings
from lp3d.photo import (
    align_face,
    crop_image,
    face_descriptor,
    find_faces,
    load_image,
    prepare_photo,
    to_encoder_input,
)
from lp3d.render.camera import camera_summary, look_at_camera
from lp3d.render.native import native_triplane
from lp3d.render.native import render as native_render
from lp3d.render.psnr import psnr_db
from lp3d.render.settings import RenderSettings

__all__ = [
    "NOVEL_YAWS_DEG",
    "SAME_PERSON_DISTANCE",
    "PhotoEval",
    "PhotoSettings",
    "ViewScore",
    "evaluate_photo",
    "summarise",
]

#: dlib's threshold: descriptors nearer than this are called one person.
SAME_PERSON_DISTANCE = 0.6
#: The novel views' yaws (degrees), pitch 0: the frontal view and two each side.
NOVEL_YAWS_DEG = (-35.0, -20.0, 0.0, 20.0, 35.0)


@dataclass(frozen=True)
class PhotoSettings:
    """How each photo is lifted and viewed: ``refine_steps`` of ``--refine`` (0: the encoder alone),
    the views' ``yaws_deg``, output side ``resolution`` (the SR network's, when there is one) and
    ``samples`` (coarse, fine)."""

    refine_steps: int = 0
    yaws_deg: tuple[float, ...] = NOVEL_YAWS_DEG
    samples: tuple[int, int] = (48, 48)
    #: How the refine fits (its ``steps`` replaced by ``refine_steps``); None: ``RefineSettings()``.
    refine: RefineSettings | None = None


@dataclass
class ViewScore:
    """One novel view: the yaw asked, whether a face was found, the ID ``distance`` and ``cosine``
    similarity to the photo, and the landmark camera's yaw on the render (None without a face)."""

    yaw_deg: float
    face_found: bool
    distance: float | None = None
    cosine: float | None = None
    found_yaw_deg: float | None = None

    @property
    def recognised(self) -> bool:
        return self.distance is not None and self.distance < SAME_PERSON_DISTANCE

    def to_dict(self) -> dict[str, Any]:
        return {
            "yaw_deg": self.yaw_deg,
            "face_found": self.face_found,
            "distance": self.distance,
            "cosine": self.cosine,
            "found_yaw_deg": self.found_yaw_deg,
            "recognised": self.recognised,
        }


@dataclass
class PhotoEval:
    """One photo's scores, with the images of its figure row (the crop and the views)."""

    name: str
    description: str
    yaw_deg: float
    pitch_deg: float
    input_psnr: float
    input_ssim: float
    input_distance: float | None
    depth_relief: float
    encoder_depth_relief: float
    views: list[ViewScore]
    images: list[np.ndarray] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "description": self.description,
            "camera": {"yaw_deg": self.yaw_deg, "pitch_deg": self.pitch_deg},
            "input_view": {
                "face_psnr_db": self.input_psnr,
                "face_ssim": self.input_ssim,
                "distance": self.input_distance,
            },
            "depth_relief": {"head": self.depth_relief, "encoder": self.encoder_depth_relief},
            "views": [v.to_dict() for v in self.views],
        }


def _descriptor_similarity(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.dot(a, b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12))


def _face_box(crop_landmarks: np.ndarray, size: int) -> tuple[int, int, int, int]:
    """The face region (x0, y0, x1, y1) of a ``size``² crop from its landmarks: a square about the eyes
    and nose, as wide as twice the outer eye corners' span."""
    centre = crop_landmarks.mean(axis=0)
    half = float(np.linalg.norm(crop_landmarks[0] - crop_landmarks[2]))
    x0, y0 = (int(np.clip(round(c - half), 0, size - 1)) for c in centre)
    x1, y1 = (int(np.clip(round(c + half), 1, size)) for c in centre)
    return x0, y0, x1, y1


def _images(
    tri: Any, cameras: np.ndarray, sr: LoadedSuperres | None, resolution: int, samples: tuple[int, int]
) -> tuple[list[np.ndarray], np.ndarray]:
    """The final images (R, R, 3) uint8 of ``cameras`` (B, 25), super-resolved when ``sr`` is given,
    and the raw depth images (B, r, r) (r: the SR network's input side, or R)."""
    settings = RenderSettings(
        resolution=sr.input_resolution if sr is not None else resolution,
        depth_resolution=samples[0],
        depth_resolution_importance=samples[1],
    )
    out = native_render(
        native_triplane(tri), cameras, settings, outputs=["features" if sr else "rgb", "depth"]
    )
    rgb = sr(out["features"]) if sr is not None else out["rgb"]
    r = settings.resolution
    return [rgb_to_uint8(x) for x in rgb], np.asarray(out["depth"]).reshape(len(cameras), r, r)


def depth_relief(depth: np.ndarray, box: tuple[int, int, int, int], size: int) -> float:
    """The spread (95th minus 5th percentile) of ``depth`` (r, r) over ``box`` (x0, y0, x1, y1), given
    in a ``size``² image's pixels: how far the face stands out, nose tip to cheeks, in world units."""
    r = depth.shape[0]
    x0, y0, x1, y1 = (int(round(v * r / size)) for v in box)
    region = depth[y0 : max(y1, y0 + 1), x0 : max(x1, x0 + 1)]
    lo, hi = np.percentile(region, [5.0, 95.0])
    return float(hi - lo)


def _score_views(
    yaws: Sequence[float], images: Sequence[np.ndarray], reference: np.ndarray
) -> list[ViewScore]:
    """Each view at its yaw against the photo's descriptor ``reference``: found, distance, pose."""
    views = []
    for y, img in zip(yaws, images, strict=True):
        faces = find_faces(img)
        if not faces:
            views.append(ViewScore(y, False))
            continue
        d = face_descriptor(img, faces[0])
        views.append(
            ViewScore(
                y,
                True,
                distance=float(np.linalg.norm(d - reference)),
                cosine=_descriptor_similarity(d, reference),
                found_yaw_deg=align_face(faces[0].landmarks).yaw_deg,
            )
        )
    return views


def evaluate_photo(
    path: Path,
    encoder: LoadedEncoder,
    sr: LoadedSuperres | None,
    settings: PhotoSettings,
    *,
    on_step: Callable[[], Any] | None = None,
) -> PhotoEval:
    """Lift the photo at ``path`` and score its views (module docstring). Raises PhotoError for a photo
    without a usable face."""
    import torch

    from lp3d.training.losses import ssim

    pkg = encoder.package
    rgb, _ = load_image(path)
    prep = prepare_photo(rgb, pkg.image_size, detect=True, name=str(path))  # NoFaceError without one
    photo_face = prep.detection
    assert photo_face is not None  # detect=True: a prepared photo has its face
    reference = face_descriptor(rgb, photo_face.face)
    tri = encoded = pkg.triplane(encoder.encode(to_encoder_input(prep.image[None]))[0])
    resolution = sr.output_resolution if sr is not None else 256
    # The photo's crop at the output's side, cut from the photo itself (not the encoder's smaller crop
    # scaled up): what the input view is scored against. The refine fits the encoder's crop, as
    # `lp3d encode --refine` does.
    crop = crop_image(rgb, photo_face.crop, resolution)
    yaw, pitch = prep.pose  # type: ignore[misc]
    camera = look_at_camera(yaw_deg=yaw, pitch_deg=pitch)
    if settings.refine_steps > 0:
        import dataclasses

        from lp3d.lift.refine import refine, superres_module

        how = dataclasses.replace(settings.refine or RefineSettings(), steps=settings.refine_steps)
        result = refine(
            tri, prep.image, how, pose=(yaw, pitch), superres=superres_module(pkg), on_step=on_step
        )
        tri, camera = result.triplane, result.camera
    cams = np.stack([camera] + [look_at_camera(yaw_deg=y) for y in settings.yaws_deg])
    images, depths = _images(tri, cams, sr, resolution, settings.samples)

    # The input view against the photo's crop, on the face region only (the backdrop is easy).
    m = photo_face.crop.matrix(resolution)
    x0, y0, x1, y1 = _face_box(photo_face.face.landmarks @ m[:, :2].T + m[:, 2], resolution)

    def face(img: np.ndarray) -> np.ndarray:
        return img[y0:y1, x0:x1].astype(np.float32) / 127.5 - 1.0

    a, b = face(images[0]), face(crop)
    input_psnr = psnr_db(a, b)
    to_t = lambda x: torch.from_numpy(x.transpose(2, 0, 1)[None].copy())  # noqa: E731
    input_ssim = float(ssim(to_t(a), to_t(b))[0])
    input_faces = find_faces(images[0])
    input_distance = (
        float(np.linalg.norm(face_descriptor(images[0], input_faces[0]) - reference)) if input_faces else None
    )
    box = (x0, y0, x1, y1)
    relief = depth_relief(depths[0], box, resolution)
    if encoded is tri:
        encoder_relief = relief
    else:
        _, encoder_depth = _images(encoded, camera[None], sr, resolution, settings.samples)
        encoder_relief = depth_relief(encoder_depth[0], box, resolution)

    views = _score_views(settings.yaws_deg, images[1:], reference)
    angles = camera_summary(camera)
    return PhotoEval(
        name=path.name,
        description=prep.description,
        yaw_deg=angles["yaw_deg"],
        pitch_deg=angles["pitch_deg"],
        input_psnr=input_psnr,
        input_ssim=input_ssim,
        input_distance=input_distance,
        depth_relief=relief,
        encoder_depth_relief=encoder_relief,
        views=views,
        images=[crop, *images[1:]],
    )


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def summarise(evals: Sequence[PhotoEval]) -> dict[str, Any]:
    """Means over photos, and per |yaw|: views with a face, views recognised, mean distance and cosine,
    median pose error."""
    out: dict[str, Any] = {
        "photos": len(evals),
        "input_face_psnr_db": _mean([e.input_psnr for e in evals]),
        "input_face_ssim": _mean([e.input_ssim for e in evals]),
        "input_distance": _mean([e.input_distance for e in evals if e.input_distance is not None]),
        # The refined head's relief as a share of the encoder's, photo by photo: below about a half,
        # the fit has flattened the face onto its photo.
        "depth_relief_ratio": _mean([e.depth_relief / max(e.encoder_depth_relief, 1e-9) for e in evals]),
        "by_yaw": {},
    }
    yaws = sorted({abs(v.yaw_deg) for e in evals for v in e.views})
    for y in yaws:
        vs = [v for e in evals for v in e.views if abs(v.yaw_deg) == y]
        found = [v for v in vs if v.face_found]
        errors = [abs(v.found_yaw_deg - v.yaw_deg) for v in found if v.found_yaw_deg is not None]
        out["by_yaw"][f"{y:g}"] = {
            "views": len(vs),
            "face_found": len(found),
            "recognised": sum(v.recognised for v in vs),
            "mean_distance": _mean([v.distance for v in found if v.distance is not None]),
            "mean_cosine": _mean([v.cosine for v in found if v.cosine is not None]),
            "median_yaw_error_deg": statistics.median(errors) if errors else None,
        }
    return out


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The summary as a Markdown table (one row per |yaw|) and the input view's line."""

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)

    lines = [
        "| yaw | views with a face | recognised (< 0.6) | mean ID distance | mean cosine "
        "| median yaw error |",
        "|---|---|---|---|---|---|",
    ]
    for y, s in summary["by_yaw"].items():
        lines.append(
            f"| ±{y}° | {s['face_found']} of {s['views']} | {s['recognised']} of {s['views']} | "
            f"{num(s['mean_distance'], '.3f')} | {num(s['mean_cosine'], '.3f')} | "
            f"{num(s['median_yaw_error_deg'], '.1f')}° |"
        )
    lines.append(
        f"input view, face region: {num(summary['input_face_psnr_db'], '.2f')} dB PSNR, "
        f"SSIM {num(summary['input_face_ssim'], '.3f')}, "
        f"ID distance {num(summary['input_distance'], '.3f')}; "
        f"face depth relief {num(summary['depth_relief_ratio'], '.2f')}× the encoder's "
        f"({summary['photos']} photos)"
    )
    return lines


def figure(evals: Sequence[PhotoEval]) -> np.ndarray:
    """One row per photo: its crop, then its views, each captioned with its yaw and ID distance
    (✓ recognised, ✗ not, "no face")."""
    from PIL import Image, ImageDraw

    rows = []
    for e in evals:
        tiles = []
        captions = ["photo"] + [
            f"{v.yaw_deg:+.0f}°  "
            + (f"d {v.distance:.2f} {'ok' if v.recognised else 'x'}" if v.face_found else "no face")
            for v in e.views
        ]
        for img, text in zip(e.images, captions, strict=True):
            canvas = Image.new("RGB", (img.shape[1], img.shape[0] + 14), (255, 255, 255))
            canvas.paste(Image.fromarray(img), (0, 14))
            ImageDraw.Draw(canvas).text((3, 1), text, fill=(0, 0, 0))
            tiles.append(np.asarray(canvas))
        rows.append(np.concatenate(tiles, axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    return np.concatenate(rows, axis=0)
