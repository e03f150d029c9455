"""Hostile environments: full disks, signals, forked processes and
huge batches, long names, an ASCII terminal and a removed working directory. Each case ended in exit 0
with a partial file, a traceback, a leftover temporary file, a hang or an abort before."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from lp3d.atomic import create_temp
from lp3d.cli import main
from lp3d.errors import UserError
from lp3d.outputs import Staged
from lp3d.render.sample_scenes import coloured_sphere
from lp3d.render.triplane_io import save_triplane

SMALL = ["--resolution", "16", "--samples", "12+12"]


@pytest.fixture
def sphere(tmp_path: Path) -> Path:
    path = tmp_path / "s.npz"
    save_triplane(path, coloured_sphere(size=8))
    return path


def lp3d(*argv: str, env: dict[str, str] | None = None, **kwargs: object) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "lp3d.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "LP3D_DEBUG": "", **(env or {})},
        **kwargs,  # type: ignore[arg-type]
    )


def lines(stderr: str) -> list[str]:
    """stderr without the progress bar's lines."""
    return [line for line in stderr.splitlines() if line.strip() and "%|" not in line]


# ======================================================================= class 7: names, encodings


def test_temporary_names_stay_short_for_any_legal_name(tmp_path: Path) -> None:
    for name in ["a" * 251 + ".png", "é" * 125 + ".png", "x." + "s" * 253]:
        assert len(os.fsencode(name)) <= 255
        tmp = create_temp(tmp_path / name)  # was "File name too long": the name grew by ~30 bytes
        assert len(os.fsencode(tmp.name)) <= 120 and tmp.name.startswith(f".{name[:8]}"), tmp.name
        tmp.unlink()
    assert create_temp(tmp_path / "x.npz").suffix == ".npz"  # the suffix writers read is kept


def test_a_240_byte_output_name_works(gpu, capsys, sphere: Path) -> None:
    out = sphere.parent / ("a" * 236 + ".png")
    code = main(["render", str(sphere), "-o", str(out), *SMALL])
    assert code == 0, capsys.readouterr().err
    assert sorted(p.name for p in sphere.parent.iterdir()) == sorted(["s.npz", out.name])


def test_an_ascii_terminal_does_not_turn_success_into_an_error(gpu, sphere: Path) -> None:
    """`rendered 16² ...` raised UnicodeEncodeError after the file was written: exit 1."""
    proc = lp3d(
        "render", str(sphere), "-o", str(sphere.parent / "v.png"), *SMALL, env={"PYTHONIOENCODING": "ascii"}
    )
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "16\\xb2" in out and (sphere.parent / "v.png").exists()


def test_a_removed_working_directory_is_named(capsys, tmp_path: Path, monkeypatch) -> None:
    """It was "error: [Errno 2] No such file or directory", naming no file."""
    sphere = tmp_path / "s.npz"
    save_triplane(sphere, coloured_sphere(size=8))
    gone = tmp_path / "gone"
    gone.mkdir()
    monkeypatch.chdir(gone)
    gone.rmdir()
    assert main(["render", str(sphere), "-o", "v.png", *SMALL]) == 1
    err = capsys.readouterr().err
    assert "lp3d render: error: output v.png: the working directory was removed" in err, err
    assert main(["render", "s.npz", "-o", str(tmp_path / "v.png")]) == 1
    assert "triplane s.npz: the working directory was removed" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.npz"]


# ================================================================================ class 3: full disks


FAKE_FFMPEG = """#!{python}
# ffmpeg on a full disk: reads its frames, leaves part of a file, says why, exits 1.
import sys
sys.stdin.buffer.read()
open(sys.argv[-1], "wb").write(b"partial")
sys.stderr.write("[out#0/mp4] Error closing file: No space left on device\\n")
sys.exit(1)
"""


def test_an_mp4_that_ffmpeg_could_not_finish_is_an_error(gpu, sphere: Path, tmp_path: Path) -> None:
    """ffmpeg's exit status was never read: exit 0, "wrote o.mp4", a partial file."""
    fake = tmp_path / "ffmpeg"
    fake.write_text(FAKE_FFMPEG.format(python=sys.executable))
    fake.chmod(0o755)
    out = tmp_path / "o.mp4"
    proc = lp3d(
        "orbit", str(sphere), "-o", str(out), "--frames", "2", *SMALL, env={"IMAGEIO_FFMPEG_EXE": str(fake)}
    )
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1 and "Traceback" not in err, err
    assert lines(err)[-1] == f"lp3d orbit: error: cannot write {out}: No space left on device", err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ffmpeg", "s.npz"]


def test_a_write_error_without_a_file_name_names_the_output(tmp_path: Path) -> None:
    """write() on a full disk raises OSError(ENOSPC) naming no file: the one line named none either."""
    out = tmp_path / "mesh.ply"
    with pytest.raises(UserError, match=f"cannot write {out}: No space left on device"), Staged() as staged:
        staged.temp(out)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert not list(tmp_path.iterdir())


@pytest.fixture
def full_disk(tmp_path: Path) -> Path:
    """An 8 KiB tmpfs (needs root and permission to mount; skipped otherwise)."""
    folder = tmp_path / "full"
    folder.mkdir()
    mount = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=8k", "tmpfs", str(folder)], capture_output=True
    )
    if mount.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {mount.stderr.decode().strip()}")
    yield folder
    subprocess.run(["umount", str(folder)], check=True)


@pytest.mark.parametrize("name", ["o.mp4", "o.gif"])
def test_orbit_on_a_full_disk_is_one_line_naming_the_file(
    gpu, sphere: Path, full_disk: Path, name: str
) -> None:
    """mp4: exit 0 with a partial file; gif: a traceback from imageio's writer."""
    out = full_disk / name
    proc = lp3d(
        "orbit", str(sphere), "-o", str(out), "--frames", "24", "--resolution", "64", "--samples", "12+12"
    )
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1 and "Traceback" not in err, err
    assert lines(err)[-1] == f"lp3d orbit: error: cannot write {out}: No space left on device", err
    assert not list(full_disk.iterdir())


def test_render_on_a_full_disk_names_the_file(gpu, capsys, sphere: Path, full_disk: Path) -> None:
    out = full_disk / "v.png"
    assert main(["render", str(sphere), "-o", str(out), "--resolution", "128", "--samples", "12+12"]) == 1
    assert f"lp3d render: error: cannot write {out}: No space left on device" in capsys.readouterr().err
    assert not list(full_disk.iterdir())


# ================================================================================== class 4: signals


def test_sigterm_during_orbit_leaves_no_temporary_file(gpu, sphere: Path) -> None:
    """The temporary .o.mp4.*.tmp.mp4 stayed behind (the process died by the signal, no clean-up)."""
    folder = sphere.parent
    proc = lp3d("orbit", str(sphere), "-o", str(folder / "o.mp4"), "--frames", "2000", *SMALL)
    deadline = time.monotonic() + 60
    while not [p for p in folder.iterdir() if p.name.startswith(".o.mp4")] and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)  # frames are being rendered and encoded
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and lines(err)[-1] == "lp3d orbit: terminated", err
    assert "Traceback" not in err
    assert sorted(p.name for p in folder.iterdir()) == ["s.npz"]


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="watches /proc/PID/maps (Linux)")
def test_ctrl_c_during_start_up_is_one_line(sphere: Path) -> None:
    """Ctrl-C while numpy was being imported ended in a traceback, or in numpy's ImportError about
    "PyCapsule_Import could not import module datetime"."""
    # As a terminal starts it: Ctrl-C at its default. A test run started in the background of a
    # non-interactive shell has SIGINT ignored, and a child would inherit that across exec.
    proc = lp3d(
        "orbit",
        str(sphere),
        "-o",
        str(sphere.parent / "o.gif"),
        *SMALL,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    maps, cmdline = Path(f"/proc/{proc.pid}/maps"), Path(f"/proc/{proc.pid}/cmdline")
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            # Until the child has exec'd, its maps are a copy of this (numpy-importing) process's:
            # a signal sent then lands before lp3d runs (a loaded machine widens that window).
            started = b"lp3d.cli" in cmdline.read_bytes()
            if started and "_multiarray_umath" in maps.read_text():  # numpy is being imported
                break
        except OSError:
            pass
        time.sleep(0.001)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and lines(err) == ["lp3d: interrupted"], err
    assert sorted(p.name for p in sphere.parent.iterdir()) == ["s.npz"]


# ================================================================================ class 5: processes


SCRIPT = """
import os, sys, time
import numpy as np
import lp3d_render
from lp3d.render.camera import look_at_camera
from lp3d.render.sample_scenes import coloured_sphere

tri = coloured_sphere(size=8).to_native()
cam = look_at_camera(yaw_deg=0.0, pitch_deg=0.0)
kw = dict(resolution=8, depth_resolution=12, depth_resolution_importance=12)
"""


def run_script(body: str) -> subprocess.CompletedProcess[str]:
    code = textwrap.dedent(SCRIPT) + textwrap.dedent(body)
    env = {**os.environ, "LP3D_DEBUG": ""}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX")
def test_rendering_in_a_forked_child_is_an_error_not_a_hang(gpu) -> None:
    """What a DataLoader with worker processes does: the child's render waited forever."""
    proc = run_script(
        """
        lp3d_render.render(tri, cam, **kw)
        pid = os.fork()
        if pid == 0:
            try:
                lp3d_render.render(tri, cam, **kw)
                print("child rendered")
            except RuntimeError as e:
                print("child:", e)
            sys.stdout.flush()
            os._exit(0)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and os.waitpid(pid, os.WNOHANG) == (0, 0):
            time.sleep(0.05)
        else:
            if time.monotonic() >= deadline:
                os.kill(pid, 9)
                print("child hung")
        """
    )
    assert "child hung" not in proc.stdout, proc.stdout + proc.stderr
    assert "was forked from process" in proc.stdout and "'spawn'" in proc.stdout, proc.stdout + proc.stderr


def test_a_batch_too_large_for_memory_is_a_clear_error(gpu) -> None:
    """1,000 cameras at 1024²: "memory allocation of 134217728000 bytes failed", abort (signal 6)."""
    proc = run_script(
        """
        from lp3d_render import _guard
        _guard._memory_bytes = lambda: 64 << 30  # the same answer on any machine
        try:
            lp3d_render.render(tri, np.stack([cam] * 1000), resolution=1024)
        except ValueError as e:
            print(e)
        """
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "camera: a batch of 1000 cameras at 1024² needs 289.1 GiB" in proc.stdout, proc.stdout
    assert "render fewer cameras per call" in proc.stdout
