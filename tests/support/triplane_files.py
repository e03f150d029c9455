"""Hostile and edge-case triplane files, as data: the shared set both readers must agree on
(``tests/render/test_triplane_files.py``) and the seeds of the fuzzers
(``tests/robustness/test_triplane_fuzz.py``).

Each :class:`Case` writes one file (or names a special path) and says what both readers must do:
accept it, or refuse it with an error (OSError or ValueError) naming the file and, where there is
one, the key. ``docs/reliability.md`` counts :data:`CASES`. Files are built byte by byte here
(:func:`build_zip`, :func:`npy`), independent of either reader's writer.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.triplane import TriplaneData, occupancy_checksum
from lp3d.render.triplane_io import load_triplane

# ------------------------------------------------------------------------------------- file builders


@dataclass
class Entry:
    """One zip entry; the ``declared_*`` fields override what the central directory claims."""

    name: str
    data: bytes
    method: int = 0  # 0 stored, 8 deflated
    flags: int = 0
    declared_size: int | None = None
    declared_csize: int | None = None
    zip64: bool = False


def build_zip(entries: list[Entry]) -> bytes:
    """A zip archive written by hand: local headers, central directory (zip64 extras where a size
    needs one or ``zip64`` asks for one) and end record."""
    out, central = bytearray(), bytearray()
    for e in entries:
        payload = zlib.compress(e.data)[2:-4] if e.method == 8 else e.data
        crc = zlib.crc32(e.data)
        size = len(e.data) if e.declared_size is None else e.declared_size
        csize = len(payload) if e.declared_csize is None else e.declared_csize
        zip64 = e.zip64 or size >= 0xFFFFFFFF or csize >= 0xFFFFFFFF
        extra = struct.pack("<HHQQ", 1, 16, size, csize) if zip64 else b""
        s32, c32 = (0xFFFFFFFF, 0xFFFFFFFF) if zip64 else (size, csize)
        version = 45 if zip64 else 20
        name = e.name.encode()
        offset = len(out)
        out += struct.pack(
            "<IHHHHHIIIHH",
            0x04034B50,
            version,
            e.flags,
            e.method,
            0,
            0x21,
            crc,
            c32,
            s32,
            len(name),
            len(extra),
        )
        out += name + extra + payload
        central += struct.pack(
            "<IHHHHHHIIIHHHHHII",
            0x02014B50,
            version,
            version,
            e.flags,
            e.method,
            0,
            0x21,
            crc,
            c32,
            s32,
            len(name),
            len(extra),
            0,
            0,
            0,
            0,
            offset,
        )
        central += name + extra
    n = len(entries)
    cd_offset = len(out)
    out += central
    out += struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central), cd_offset, 0)
    return bytes(out)


def npy(header: str, body: bytes, version: tuple[int, int] = (1, 0)) -> bytes:
    """A ``.npy`` with this header text (padded as numpy pads it) and body."""
    prefix = 10 if version[0] == 1 else 12
    text = header + " " * ((64 - (prefix + len(header) + 1) % 64) % 64) + "\n"
    length = struct.pack("<H" if version[0] == 1 else "<I", len(text))
    return b"\x93NUMPY" + bytes(version) + length + text.encode("latin-1") + body


def npy_of(arr: np.ndarray, version: tuple[int, int] | None = None) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, version=version, allow_pickle=True)
    return buf.getvalue()


def good_arrays(
    dtype: type = np.float32, size: tuple[int, int] = (6, 7), seed: int = 1
) -> dict[str, np.ndarray]:
    """The arrays of a valid file (effective decoder weights, FFHQ bounds)."""
    rng = np.random.default_rng(seed)
    return {
        "planes": rng.normal(size=(3, 32, *size)).astype(dtype),
        "decoder_w0": rng.normal(size=(64, 32)).astype(np.float32),
        "decoder_b0": rng.normal(size=64).astype(np.float32),
        "decoder_w1": rng.normal(size=(33, 64)).astype(np.float32),
        "decoder_b1": rng.normal(size=33).astype(np.float32),
        "box_warp": np.array(1.0),
        "ray_start": np.array(2.25),
        "ray_end": np.array(3.3),
        "format_version": np.array(1),
    }


def npz_bytes(arrays: dict[str, np.ndarray | bytes], **entry_options: dict[str, object]) -> bytes:
    """An uncompressed ``.npz`` of ``arrays`` (raw ``bytes`` values are used as the ``.npy`` as is);
    ``entry_options[key]`` overrides that entry's :class:`Entry` fields."""
    entries = []
    for key, value in arrays.items():
        data = value if isinstance(value, bytes) else npy_of(value)
        entries.append(Entry(f"{key}.npy", data, **entry_options.get(key, {})))  # type: ignore[arg-type]
    return build_zip(entries)


def with_grid(arrays: dict[str, np.ndarray], checksum_dtype: type = np.int64) -> dict[str, np.ndarray]:
    """``arrays`` plus a valid occupancy grid and its checksum."""
    tri = TriplaneData(
        planes=arrays["planes"],
        w0=arrays["decoder_w0"],
        b0=arrays["decoder_b0"],
        w1=arrays["decoder_w1"],
        b1=arrays["decoder_b1"],
    )
    return {
        **arrays,
        "occupancy": np.full((4, 4, 4), 100.0, np.float32),
        "occupancy_checksum": np.array(occupancy_checksum(tri), checksum_dtype),
    }


def changed(**changes: np.ndarray | bytes | None) -> bytes:
    """A valid file with some keys replaced (``None`` drops the key)."""
    arrays: dict[str, np.ndarray | bytes] = {
        **good_arrays(),
        **{k: v for k, v in changes.items() if v is not None},
    }
    for k, v in changes.items():
        if v is None:
            del arrays[k]
    return npz_bytes(arrays)


def planes_header(shape: str, descr: str = "<f4", fortran: str = "False") -> str:
    return f"{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}"


# ------------------------------------------------------------------------------------------- readers


def outcome(reader: str, path: Path) -> tuple[str, object]:
    """("ok", the triplane) or (exception kind, message); anything else propagates (a test failure)."""
    try:
        tri = load_triplane(path) if reader == "python" else lp3d_render.Triplane.load(path)
    except OSError as e:
        return "OSError", str(e)
    except ValueError as e:
        return "ValueError", str(e)
    return "ok", tri


def assert_same_triplane(py: object, rs: object) -> None:
    np.testing.assert_array_equal(py.planes, rs.planes)
    assert py.planes.dtype == rs.planes.dtype
    for name in ("w0", "b0", "w1", "b1"):
        np.testing.assert_array_equal(getattr(py, name), getattr(rs, name))
    for name in ("box_warp", "ray_start", "ray_end"):
        assert np.float32(getattr(py, name)) == getattr(rs, name), name
    assert py.source == rs.source
    assert (py.camera is None) == (rs.camera is None)
    if py.camera is not None:
        np.testing.assert_array_equal(py.camera.astype(np.float32), rs.camera)
    assert (py.occupancy is None) == (rs.occupancy is None)
    if py.occupancy is not None:
        np.testing.assert_array_equal(py.occupancy, rs.occupancy)


# --------------------------------------------------------------------------------------------- cases


@dataclass(frozen=True)
class Case:
    """One file both readers must judge alike.

    ``make(folder)`` writes the file into ``folder`` and returns its path (or returns a special path
    such as ``/dev/zero``). ``field`` is None for a valid file, else the key the error must name
    ('' for the file as a whole). ``error`` is the exception both must raise. ``isolate``: the old
    readers crashed (abort, panic) or hung on it, so it runs in a subprocess with a time limit.
    ``item``: the issue-11 item it covers (0: a baseline case)."""

    name: str
    make: Callable[[Path], Path]
    field: str | None = None
    error: type[Exception] = ValueError
    words: str = ""
    isolate: bool = False
    item: int = 0

    @property
    def valid(self) -> bool:
        return self.field is None


def file_of(name: str, data: Callable[[], bytes]) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / f"{name}.npz"
        path.write_bytes(data())
        return path

    return make


def special(path: str) -> Callable[[Path], Path]:
    return lambda folder: Path(path)


def make_fifo(folder: Path) -> Path:
    path = folder / "pipe.npz"
    os.mkfifo(path)
    return path


def make_dir(folder: Path) -> Path:
    path = folder / "folder.npz"
    path.mkdir()
    return path


def make_symlink(folder: Path) -> Path:
    target = folder / "target.npz"
    target.write_bytes(npz_bytes(good_arrays()))
    link = folder / "link.npz"
    link.symlink_to(target)
    return link


def _int32_checksum_file() -> bytes:
    # A checksum stored as int32 (any 0-d integer is accepted): pick planes whose CRC fits.
    for seed in range(100):
        arrays = with_grid(good_arrays(seed=seed))
        if arrays["occupancy_checksum"] < 2**31:
            return npz_bytes(with_grid(good_arrays(seed=seed), np.int32))
    raise AssertionError("no seed gives a CRC below 2**31")


def _unicode(text_units: list[int]) -> bytes:
    return npy(
        f"{{'descr': '<U{len(text_units)}', 'fortran_order': False, 'shape': (), }}",
        struct.pack(f"<{len(text_units)}I", *text_units),
    )


def _planes_bytes() -> bytes:
    return good_arrays()["planes"].tobytes()


def _zip64_claim(size: int, csize: int | None = None) -> bytes:
    arrays = good_arrays()
    return npz_bytes(
        arrays, planes={"declared_size": size, "declared_csize": size if csize is None else csize}
    )


def _camera_far() -> np.ndarray:
    cam = look_at_camera(yaw_deg=10.0).copy()
    cam[3] = 1e300  # translation x: finite in float64, infinite in float32
    return cam


def _many_entries() -> bytes:
    arrays: dict[str, np.ndarray | bytes] = dict(good_arrays())
    for i in range(40):
        arrays[f"extra{i}"] = np.zeros(1)
    return npz_bytes(arrays)


def _duplicate_planes() -> bytes:
    arrays = good_arrays()
    entries = [Entry(f"{k}.npy", npy_of(v)) for k, v in arrays.items()]
    entries.append(Entry("planes.npy", npy_of(np.zeros_like(arrays["planes"]))))
    return build_zip(entries)


def _truncated() -> bytes:
    data = npz_bytes(good_arrays())
    return data[: len(data) // 2]


def _crc_flipped() -> bytes:
    data = bytearray(npz_bytes(good_arrays()))
    at = bytes(data).find(_planes_bytes()[:64])
    data[at + 100] ^= 0xFF
    return bytes(data)


def _valid_rust_written(folder: Path) -> Path:
    a = good_arrays(np.float16)
    tri = lp3d_render.Triplane(
        a["planes"], a["decoder_w0"], a["decoder_b0"], a["decoder_w1"], a["decoder_b1"], source="rust writer"
    )
    path = folder / "rust.npz"
    tri.save(path)
    return path


def _valid_python_written(folder: Path) -> Path:
    from lp3d.render.triplane_io import save_triplane

    a = with_grid(good_arrays())
    tri = TriplaneData(
        planes=a["planes"],
        w0=a["decoder_w0"],
        b0=a["decoder_b0"],
        w1=a["decoder_w1"],
        b1=a["decoder_b1"],
        camera=look_at_camera(yaw_deg=10.0),
        occupancy=a["occupancy"],
        occupancy_checksum=int(a["occupancy_checksum"]),
        source="python writer — ünïcode",
    )
    path = folder / "python.npz"
    save_triplane(path, tri)
    return path


_HUGE_SHAPE = "(3, 32, 65536, 65536)"

CASES: list[Case] = [
    # ---- valid files: both readers accept them and read the same values.
    Case("valid_float32", file_of("valid_float32", lambda: npz_bytes(good_arrays()))),
    Case("valid_float16_planes", file_of("valid_f16", lambda: npz_bytes(good_arrays(np.float16)))),
    Case("valid_python_writer_all_keys", _valid_python_written),
    Case("valid_rust_writer", _valid_rust_written),
    Case(
        "valid_float64_decoder",
        file_of("valid_f64", lambda: changed(decoder_w0=good_arrays()["decoder_w0"].astype(np.float64))),
    ),
    Case(
        "valid_integer_and_half_scalars",
        file_of(
            "valid_int",
            lambda: changed(
                box_warp=np.array(1, np.int64),
                ray_start=np.array(2, np.int32),
                ray_end=np.array(3.25, np.float16),
            ),
        ),
    ),
    Case(
        "valid_int32_format_version",
        file_of("valid_v32", lambda: changed(format_version=np.array(1, np.int32))),
    ),
    Case("valid_int32_checksum", file_of("valid_crc32", _int32_checksum_file)),
    Case("valid_planes_2x2", file_of("valid_2x2", lambda: npz_bytes(good_arrays(size=(2, 2))))),
    Case(
        "valid_plane_side_at_cap",
        file_of("valid_2048", lambda: npz_bytes(good_arrays(np.float16, size=(2048, 2)))),
    ),
    Case("valid_source_at_cap", file_of("valid_src", lambda: changed(source=np.array("x" * 4096)))),
    Case("valid_source_inner_nul", file_of("valid_nul", lambda: changed(source=_unicode([97, 0, 98, 0])))),
    Case(
        "valid_npy_version_2_header",
        file_of("valid_npy2", lambda: changed(planes=npy_of(good_arrays()["planes"], version=(2, 0)))),
    ),
    Case("valid_symlink", make_symlink),
    # ---- item 3: not a regular file. Both must refuse at once, naming the file, never hang.
    Case("directory", make_dir, "", OSError, "is a directory", item=3),
    Case("fifo", make_fifo, "", OSError, "FIFO", isolate=True, item=3),
    Case("dev_zero", special("/dev/zero"), "", OSError, "character device", isolate=True, item=3),
    Case("dev_urandom", special("/dev/urandom"), "", OSError, "character device", isolate=True, item=3),
    Case("empty_file", file_of("empty", lambda: b""), "", ValueError, "empty", item=3),
    # ---- items 1 and 4: size claims are checked before anything is allocated.
    Case(
        "zip64_claims_1_tib",
        file_of("z64_tb", lambda: _zip64_claim(1 << 40)),
        "planes",
        words="cap",
        isolate=True,
        item=1,
    ),
    Case(
        "zip64_claims_2pow64_minus_16",
        file_of("z64_max", lambda: _zip64_claim(2**64 - 16)),
        "planes",
        words="cap",
        isolate=True,
        item=1,
    ),
    Case(
        "zip64_size_disagrees_with_stored_size",
        file_of("z64_mixed", lambda: _zip64_claim(1 << 40, len(npy_of(good_arrays()["planes"])))),
        "planes",
        isolate=True,
        item=1,
    ),
    Case(
        "entry_size_past_end_of_file",
        file_of(
            "past_eof",
            lambda: npz_bytes(
                good_arrays(), planes={"declared_size": 100 << 20, "declared_csize": 100 << 20}
            ),
        ),
        "planes",
        words="past the end",
        item=1,
    ),
    Case(
        "npy_header_claims_1_5_tib",
        file_of("huge_shape", lambda: changed(planes=npy(planes_header(_HUGE_SHAPE), _planes_bytes()))),
        "planes",
        words="truncated",
        item=4,
    ),
    Case(
        "npy_header_shape_overflows",
        file_of(
            "overflow",
            lambda: changed(planes=npy(planes_header("(3, 32, 4294967296, 4294967296)", "<f8"), b"")),
        ),
        "planes",
        words="too large",
        item=4,
    ),
    Case(
        "npy_header_shape_overflows_before_a_zero",
        file_of(
            "overflow0",
            lambda: changed(decoder_b0=npy(planes_header("(4294967296, 4294967296, 0)"), b"")),
        ),
        "decoder_b0",
        words="too large",
        item=4,
    ),
    Case(
        "planes_4096_claimed",
        file_of("p4096", lambda: changed(planes=npy(planes_header("(3, 32, 4096, 4096)"), _planes_bytes()))),
        "planes",
        item=4,
    ),
    Case(
        "plane_side_over_cap",
        file_of("p2050", lambda: npz_bytes(good_arrays(np.float16, size=(2050, 2)))),
        "planes",
        words="2048",
        item=4,
    ),
    Case(
        "occupancy_grid_over_cap",
        file_of(
            "g513",
            lambda: npz_bytes(
                {**with_grid(good_arrays()), "occupancy": npy(planes_header("(513, 513, 513)"), b"")}
            ),
        ),
        "occupancy",
        item=4,
    ),
    Case(
        "source_over_cap",
        file_of("src_long", lambda: changed(source=np.array("x" * 4097))),
        "source",
        words="4096",
        item=4,
    ),
    Case(
        "npy_header_length_over_cap",
        file_of(
            "hdr_cap", lambda: changed(planes=b"\x93NUMPY\x02\x00" + struct.pack("<I", 0xFFFFFFF0) + b"{}")
        ),
        "planes",
        words="cap",
        item=4,
    ),
    Case("too_many_entries", file_of("many", _many_entries), "", words="cap", item=4),
    Case("duplicate_entry_name", file_of("dup", _duplicate_planes), "", words="twice", item=8),
    Case(
        "trailing_bytes_after_data",
        file_of("trailing", lambda: changed(decoder_b1=npy_of(good_arrays()["decoder_b1"]) + b"\0" * 4)),
        "decoder_b1",
        words="unexpected bytes",
        item=8,
    ),
    # ---- item 8: one spec for both readers.
    Case(
        "box_warp_shape_1",
        file_of("bw1", lambda: changed(box_warp=np.array([1.0]))),
        "box_warp",
        words="shape",
        item=8,
    ),
    Case(
        "format_version_shape_1",
        file_of("fv1", lambda: changed(format_version=np.array([1]))),
        "format_version",
        item=8,
    ),
    Case("source_shape_1", file_of("src1", lambda: changed(source=np.array(["abc"]))), "source", item=8),
    Case(
        "float16_decoder_weights",
        file_of("w0f16", lambda: changed(decoder_w0=good_arrays()["decoder_w0"].astype(np.float16))),
        "decoder_w0",
        words="dtype",
        item=8,
    ),
    Case(
        "absurd_unicode_dtype",
        file_of(
            "u_absurd",
            lambda: changed(
                source=npy(
                    "{'descr': '<U4611686018427387904', 'fortran_order': False, 'shape': (), }", b"abcd"
                )
            ),
        ),
        "source",
        words="unsupported dtype",
        item=8,
    ),
    Case(
        "fortran_order_planes",
        file_of(
            "fortran",
            lambda: changed(planes=npy(planes_header("(3, 32, 6, 7)", fortran="True"), _planes_bytes())),
        ),
        "planes",
        words="Fortran",
        item=8,
    ),
    Case(
        "big_endian_planes",
        file_of("big_endian", lambda: changed(planes=good_arrays()["planes"].astype(">f4"))),
        "planes",
        words="unsupported dtype",
        item=8,
    ),
    Case(
        "uint8_scalar", file_of("u8", lambda: changed(ray_start=np.array(2, np.uint8))), "ray_start", item=8
    ),
    Case(
        "ray_end_1e300",
        file_of("re300", lambda: changed(ray_end=np.array(1e300))),
        "ray_end",
        words="float32",
        item=8,
    ),
    Case(
        "box_warp_1e300",
        file_of("bw300", lambda: changed(box_warp=np.array(1e300))),
        "box_warp",
        words="float32",
        item=8,
    ),
    Case(
        "box_warp_zero_in_float32",
        file_of("bw_tiny", lambda: changed(box_warp=np.array(1e-50))),
        "box_warp",
        item=8,
    ),
    Case(
        "ray_start_negative_tiny",
        file_of("rs_neg", lambda: changed(ray_start=np.array(-1e-50))),
        "ray_start",
        item=8,
    ),
    Case(
        "ray_end_equal_in_float32",
        file_of("re_eq", lambda: changed(ray_end=np.array(2.25 + 1e-12))),
        "ray_end",
        item=8,
    ),
    Case(
        "camera_translation_1e300",
        file_of("cam300", lambda: changed(camera=_camera_far())),
        "camera",
        words="float32",
        item=8,
    ),
    Case(
        "compressed_npz",
        file_of("deflated", lambda: _savez_compressed(good_arrays())),
        "planes",
        words="compressed",
        item=8,
    ),
    Case(
        "encrypted_entry",
        file_of("crypt", lambda: npz_bytes(good_arrays(), planes={"flags": 1})),
        "planes",
        words="encrypted",
        item=8,
    ),
    Case(
        "format_version_2_with_new_key",
        file_of("v2", lambda: changed(format_version=np.array(2), future_key=np.zeros(3))),
        "format_version",
        words="unknown format_version 2 ",
        item=8,
    ),
    Case(
        "format_version_float",
        file_of("vf", lambda: changed(format_version=np.array(1.0))),
        "format_version",
        item=8,
    ),
    Case(
        "source_invalid_code_point",
        file_of("surrogate", lambda: changed(source=_unicode([0xD800]))),
        "source",
        words="unicode",
        item=8,
    ),
    # ---- baseline: what both readers refused before, kept so it stays so.
    Case("not_a_zip", file_of("text", lambda: b"hello, this is not a triplane at all\n" * 10), ""),
    Case("single_npy_file", file_of("single", lambda: npy_of(np.zeros(3))), ""),
    Case("truncated_archive", file_of("trunc", _truncated), ""),
    Case("crc_mismatch", file_of("crc", _crc_flipped), "planes"),
    Case("missing_planes", file_of("missing", lambda: changed(planes=None)), "planes", words="missing"),
    Case(
        "missing_format_version",
        file_of("no_version", lambda: changed(format_version=None)),
        "format_version",
        words="missing",
    ),
    Case("unknown_key", file_of("extra", lambda: changed(notes=np.zeros(2))), "notes", words="unknown key"),
    Case(
        "object_array",
        file_of("object", lambda: changed(planes=np.array([1, "a", None], dtype=object))),
        "planes",
        words="object",
    ),
    Case(
        "planes_nan",
        file_of("nan", lambda: changed(planes=np.full((3, 32, 6, 7), np.nan, np.float32))),
        "planes",
        words="NaN",
    ),
    Case(
        "npy_bad_magic",
        file_of("magic", lambda: changed(decoder_b0=b"\x93NUMPX" + npy_of(good_arrays()["decoder_b0"])[6:])),
        "decoder_b0",
        words="magic",
    ),
    Case(
        "npy_header_not_ascii",
        file_of(
            "latin",
            lambda: changed(
                decoder_b0=npy("{'descr': '<f4', 'fortran_order': False, 'shape': (64,), } \xe9", b"\0" * 256)
            ),
        ),
        "decoder_b0",
    ),
    Case(
        "npy_shape_without_tuple_comma",
        file_of(
            "nocomma",
            lambda: changed(
                decoder_b0=npy("{'descr': '<f4', 'fortran_order': False, 'shape': (64), }", b"\0" * 256)
            ),
        ),
        "decoder_b0",
    ),
    Case(
        "npy_header_duplicate_key",
        file_of(
            "dupkey",
            lambda: changed(
                decoder_b0=npy(
                    "{'descr': '<f8', 'descr': '<f4', 'fortran_order': False, 'shape': (64,), }", b"\0" * 256
                )
            ),
        ),
        "decoder_b0",
    ),
    Case(
        "string_for_a_number",
        file_of("str_num", lambda: changed(ray_start=np.array("2.25"))),
        "ray_start",
        words="dtype",
    ),
    Case(
        "occupancy_without_checksum",
        file_of("no_crc", lambda: npz_bytes({**good_arrays(), "occupancy": np.ones((4, 4, 4), np.float32)})),
        "occupancy_checksum",
    ),
]


def _savez_compressed(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def count_by_item() -> dict[int, int]:
    """Cases per issue-11 item (0: baseline), for docs/reliability.md."""
    counts: dict[int, int] = {}
    for case in CASES:
        counts[case.item] = counts.get(case.item, 0) + 1
    return counts
