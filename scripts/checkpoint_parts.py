"""A training run's student weights in parts no larger than a limit, and the parts joined back.

Why: a GPU machine that hands back only small files (docs/training.md, "Continuing the shipped model
on one GPU") cannot return a whole checkpoint, which holds the weights and twice that of Adam's
state. The weights alone are what ``lp3d eval``, ``lp3d export`` and ``--init-from`` read;
``--resume`` needs the optimiser's state and refuses such a checkpoint.

    python scripts/checkpoint_parts.py split RUN_OR_CHECKPOINT OUT_DIR [--part-mib 15]
    python scripts/checkpoint_parts.py join OUT_DIR/step-NNNNNN.parts.json runs/x/checkpoints/step-NNNNNN.pt

``split`` reads the checkpoint as ``lp3d eval`` does (a run folder: its newest readable one), keeps
what rebuilding the student needs (``lp3d.training.checkpoint.weights_only_checkpoint``: its
configuration, teacher, scene bounds, step and weights) and writes ``step-NNNNNN.part00``,
``.part01``, ... and, last, the manifest ``step-NNNNNN.parts.json`` with every part's size and
SHA-256 and the whole file's. ``join`` checks each part and the whole against the manifest before
anything is written, and publishes the checkpoint only once it loads as one (atomically: never half
a file under its name).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import re
import sys
from pathlib import Path

PARTS_FORMAT = "lp3d-checkpoint-parts-v1"
#: Part and manifest names: letters, digits, '.', '_' and '-' alone, safe on any file system and copy tool.
SAFE_NAME = re.compile(r"^[A-Za-z0-9._-]{1,100}$")
MAX_PARTS = 256
#: Largest part (``--part-mib`` goes up to 4096) and largest manifest (256 parts take ~40 KB).
MAX_PART_BYTES = 4096 << 20
MAX_MANIFEST_BYTES = 1 << 20


class PartsError(ValueError):
    """Parts or a manifest that cannot be joined (named in the message)."""


def _sha256(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def split(source: Path, out_dir: Path, part_bytes: int) -> Path:
    """Write the weights of ``source`` (a checkpoint or a run folder) as parts of at most
    ``part_bytes`` into ``out_dir``; returns the manifest's path."""
    import torch

    from lp3d.atomic import atomic_path, atomic_write_text
    from lp3d.training.checkpoint import load_checkpoint, weights_only_checkpoint

    if part_bytes < 1:
        raise PartsError(f"the part size must be at least 1 byte, got {part_bytes}")
    if out_dir.exists() and not out_dir.is_dir():
        raise PartsError(f"the output folder {str(out_dir)!r} is a file, not a folder")
    ckpt = load_checkpoint(source)  # checks its entries: a step number, a student, ...
    step = int(ckpt["step"])
    buf = io.BytesIO()
    torch.save(weights_only_checkpoint(ckpt), buf)
    data = buf.getbuffer()
    n_parts = -(-len(data) // part_bytes)
    if n_parts > MAX_PARTS:
        raise PartsError(f"{n_parts} parts of {part_bytes} bytes: more than {MAX_PARTS}; choose larger parts")
    stem = f"step-{step:06d}"
    parts = []
    for i in range(n_parts):
        chunk = data[i * part_bytes : (i + 1) * part_bytes]
        name = f"{stem}.part{i:02d}"
        with atomic_path(out_dir / name) as tmp:
            tmp.write_bytes(chunk)
        parts.append({"name": name, "bytes": len(chunk), "sha256": _sha256(chunk)})
    manifest = {
        "format": PARTS_FORMAT,
        "file": f"{stem}.pt",
        "bytes": len(data),
        "sha256": _sha256(data),
        "step": step,
        "config": ckpt["train_config"].name,
        "source": str(ckpt["path"]),
        "parts": parts,
    }
    path = out_dir / f"{stem}.parts.json"
    atomic_write_text(path, json.dumps(manifest, indent=2) + "\n")  # last: a manifest means all parts
    return path


def _read_bounded(path: Path, what: str, max_bytes: int) -> bytes:
    """The bytes of ``path`` through lp3d's one bounded reader: a regular file (a FIFO or a device is
    refused at once, never read) of at most ``max_bytes``, as a PartsError naming it."""
    from lp3d.render.npz_reader import read_regular_file

    try:
        return read_regular_file(path, what, max_bytes)
    except OSError as e:
        raise PartsError(f"{what} {str(path)!r} cannot be read: {e.strerror or e}") from None
    except ValueError as e:
        raise PartsError(str(e)) from None


def _read_manifest(path: Path) -> dict:
    from lp3d.lift.sidecar import parse_json

    raw = _read_bounded(path, "a manifest", MAX_MANIFEST_BYTES)
    try:
        manifest = parse_json(path, raw.decode("utf-8"), "manifest")  # nesting, huge numbers
    except (ValueError, UnicodeDecodeError) as e:
        raise PartsError(f"manifest {str(path)!r} is not JSON: {e}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != PARTS_FORMAT:
        raise PartsError(f"{str(path)!r} is not a manifest of format {PARTS_FORMAT!r}")
    parts = manifest.get("parts")
    if not isinstance(parts, list) or not 1 <= len(parts) <= MAX_PARTS:
        raise PartsError(f"manifest {str(path)!r}: 'parts' must list 1 to {MAX_PARTS} parts")
    for i, p in enumerate(parts):
        ok = (
            isinstance(p, dict)
            and isinstance(p.get("name"), str)
            and SAFE_NAME.match(p["name"]) is not None
            and type(p.get("bytes")) is int
            and 0 <= p["bytes"] <= MAX_PART_BYTES
            and isinstance(p.get("sha256"), str)
        )
        if not ok:
            raise PartsError(f"manifest {str(path)!r}: part {i} needs a plain file name, bytes and sha256")
    if type(manifest.get("bytes")) is not int or not isinstance(manifest.get("sha256"), str):
        raise PartsError(f"manifest {str(path)!r}: the whole file's 'bytes' and 'sha256' are missing")
    if sum(p["bytes"] for p in parts) != manifest["bytes"]:
        raise PartsError(f"manifest {str(path)!r}: its parts' sizes do not add up to 'bytes'")
    return manifest


def join(manifest_path: Path, dest: Path) -> Path:
    """Check the parts listed in ``manifest_path`` (beside it) and write the checkpoint they make
    to ``dest``; returns ``dest``."""
    from lp3d.atomic import atomic_path
    from lp3d.training.checkpoint import CheckpointError, load_checkpoint

    manifest = _read_manifest(manifest_path)
    folder = manifest_path.parent
    inputs = {manifest_path.resolve(), *((folder / p["name"]).resolve() for p in manifest["parts"])}
    if dest.resolve() in inputs:
        raise PartsError(f"the output {str(dest)!r} is one of the parts or the manifest: choose another path")
    if dest.is_dir():
        raise PartsError(f"the output {str(dest)!r} is a folder: name the checkpoint file to write")
    chunks = []
    for p in manifest["parts"]:
        part = folder / p["name"]
        data = _read_bounded(
            part, "a checkpoint part", p["bytes"]
        )  # a longer file is refused before it is read
        if len(data) != p["bytes"] or _sha256(data) != p["sha256"]:
            raise PartsError(f"part {str(part)!r} is not the one the manifest lists (size or SHA-256 differ)")
        chunks.append(data)
    whole = b"".join(chunks)
    if _sha256(whole) != manifest["sha256"]:
        raise PartsError(f"the parts of {str(manifest_path)!r} join to another file than the manifest's")
    with atomic_path(dest) as tmp:
        tmp.write_bytes(whole)
        try:
            ckpt = load_checkpoint(tmp)
        except CheckpointError as e:
            raise PartsError(f"the joined file is not a readable checkpoint: {e}") from None
        if "student" not in ckpt:
            raise PartsError("the joined checkpoint holds no student weights")
    return dest


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("split", help="a checkpoint's weights in parts, with a manifest")
    s.add_argument("source", type=Path, help="a checkpoint file or a run folder (its newest checkpoint)")
    s.add_argument("out_dir", type=Path, help="folder for the parts and the manifest")
    s.add_argument("--part-mib", type=float, default=15.0, help="largest part in MiB (default 15)")
    j = sub.add_parser("join", help="the parts a manifest lists, checked, as one checkpoint")
    j.add_argument("manifest", type=Path, help="the .parts.json written by split (its parts beside it)")
    j.add_argument("dest", type=Path, help="the checkpoint file to write")
    args = p.parse_args(argv)
    from lp3d.errors import safe_text
    from lp3d.training.checkpoint import CheckpointError

    try:
        if args.command == "split":
            if not 0 < args.part_mib <= 4096:
                p.error("--part-mib must be in (0, 4096]")
            path = split(args.source, args.out_dir, int(args.part_mib * 2**20))
            manifest = json.loads(path.read_text())
            n, size = len(manifest["parts"]), manifest["bytes"]
            print(f"{n} parts, {size} bytes of step {manifest['step']}: {path}")
        else:
            join(args.manifest, args.dest)
            print(f"wrote {args.dest}")
    except (PartsError, CheckpointError) as e:
        print(f"checkpoint_parts: error: {safe_text(str(e))}", file=sys.stderr)
        return 1
    except OSError as e:  # writing a part or the checkpoint: a full disk, a read-only folder
        print(f"checkpoint_parts: error: {safe_text(f'{e.filename}: {e.strerror or e}')}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
