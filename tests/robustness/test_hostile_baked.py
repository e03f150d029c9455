"""Hostile baked-field files and arguments: :func:`lp3d.render.baked.load_baked` reads through the
project's one bounded ``.npz`` reader (a regular file, every size checked before it is allocated),
refuses what the format does not allow by name, and ``lp3d_render.attach_baked`` takes its numbers
through the renderer's one validating conversion. Each test failed before (a hang, a MemoryError, an
OverflowError, a silent truncation, or a message without the file)."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from lp3d.render.baked import load_baked
from support.baked_files import K, arrays_of, baked_bytes, claiming, small_baked
from support.triplane_files import npy_of


@pytest.fixture(scope="module")
def baked(tmp_path_factory, gpu) -> tuple[object, Path]:
    return small_baked(tmp_path_factory.mktemp("baked"))


def _file(folder: Path, name: str, data: bytes) -> Path:
    path = folder / name
    path.write_bytes(data)
    return path


def test_a_fifo_is_refused_at_once_not_read(baked, tmp_path) -> None:
    tri, _ = baked
    fifo = tmp_path / "pipe.baked.npz"
    os.mkfifo(fifo)
    result: list[BaseException | None] = []

    def load() -> None:
        try:
            load_baked(fifo, tri)
            result.append(None)
        except BaseException as e:  # noqa: BLE001  (the test reports whatever it was)
            result.append(e)

    worker = threading.Thread(target=load, daemon=True)
    worker.start()
    worker.join(20)
    if worker.is_alive():  # free the reader so the thread ends
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)
        pytest.fail("load_baked of a FIFO waited for a writer")
    assert isinstance(result[0], OSError) and "FIFO" in str(result[0]) and str(fifo) in str(result[0])


def test_a_folder_and_a_device_are_named(baked, tmp_path) -> None:
    tri, _ = baked
    with pytest.raises(IsADirectoryError, match="is a directory"):
        load_baked(tmp_path, tri)
    with pytest.raises(OSError, match="/dev/zero: is a character device"):
        load_baked("/dev/zero", tri)


@pytest.mark.parametrize(
    ("key", "shape"),
    [("values", "(1099511627776, 3, 3, 3, 4)"), ("index", "(100000, 100000, 100000)")],
)
def test_a_header_claiming_terabytes_is_refused_before_allocation(baked, tmp_path, key, shape) -> None:
    tri, path = baked
    descr = "<f2" if key == "values" else "<i8"
    bad = _file(tmp_path, "claim.npz", baked_bytes(arrays_of(path) | {key: claiming(shape, descr)}))
    with pytest.raises(ValueError, match=rf"claim\.npz: {key}: "):
        load_baked(bad, tri)


@pytest.mark.parametrize(
    ("name", "value", "words"),
    [
        ("subdivisions", np.array(1e300), "subdivisions: must be a whole number"),
        ("subdivisions", np.array(2.5), "subdivisions: must be a whole number"),
        ("fine_subdivisions", np.array(1e300), "fine_subdivisions: must be a whole number"),
        ("subdivisions", np.array(2**62), "subdivisions: must be a whole number"),
        ("occupancy_epsilon", np.array(1e300), "occupancy_epsilon"),
    ],
)
def test_numbers_out_of_range_are_refused_by_name(baked, tmp_path, name, value, words) -> None:
    tri, path = baked
    bad = _file(tmp_path, "numbers.npz", baked_bytes(arrays_of(path) | {name: value}))
    with pytest.raises(ValueError, match=rf"numbers\.npz: {words}"):
        load_baked(bad, tri)


def test_the_renderers_own_checks_name_the_file(baked, tmp_path) -> None:
    tri, path = baked
    good = arrays_of(path)
    for name, arrays, words in [
        ("index", good | {"index": np.zeros_like(good["index"])}, "index: must name bricks"),
        ("nan", good | {"values": np.full_like(good["values"], np.nan)}, "values: NaN or Inf"),
        ("k", good | {"subdivisions": np.array(K + 1)}, "subdivisions|values"),
    ]:
        bad = _file(tmp_path, f"{name}.npz", baked_bytes(arrays))
        with pytest.raises(ValueError, match=rf"{name}\.npz: .*({words})"):
            load_baked(bad, tri)


def test_unknown_keys_and_pickles_are_refused(baked, tmp_path) -> None:
    tri, path = baked
    good = arrays_of(path)
    extra = _file(tmp_path, "extra.npz", baked_bytes(good | {"notes": np.array([1.0])}))
    with pytest.raises(ValueError, match="extra.npz: notes: unknown key"):
        load_baked(extra, tri)
    objects = np.array([None, 1], dtype=object)
    pickled = _file(tmp_path, "pickled.npz", baked_bytes(good | {"values": npy_of(objects)}))
    with pytest.raises(ValueError, match="pickled.npz: values: object arrays are not allowed"):
        load_baked(pickled, tri)


def test_attach_baked_takes_its_numbers_through_the_validating_conversion(baked) -> None:
    import lp3d_render

    tri, path = baked
    good = arrays_of(path)
    args = (tri, good["index"], np.ascontiguousarray(good["values"]).view(np.uint16))
    kw = {"subdivisions": K, "occupancy_epsilon": 1e-4, "max_delta": float(good["max_delta"])}
    for name, value in [
        ("subdivisions", 2**70),
        ("fine_subdivisions", 2**70),
        ("occupancy_epsilon", 10**400),
        ("max_delta", float("nan")),
    ]:
        with pytest.raises(ValueError, match=name):
            lp3d_render.attach_baked(*args, **(kw | {name: value}))
    with pytest.raises(TypeError, match="subdivisions: must be an int"):
        lp3d_render.attach_baked(*args, **(kw | {"subdivisions": 2.5}))
    assert lp3d_render.attach_baked(*args, **kw).bricks == len(good["values"])
