"""How fast ``lp3d serve`` lifts webcam frames: server-side frames per second of align + encode,
camera-frame-to-triplane latency, and the bytes each frame costs, on the machine it runs on.

    python bench/serve_speed.py                        # the shipped model, 320x240 JPEG frames
    python bench/serve_speed.py --seconds 20 --width 640

The server is ``lp3d serve --port 0`` in a process of its own (as for the page, whose browser is
another process); one client streams the frames over the WebSocket as the page does (a frame number
and a JPEG per message). The frames are scikit-image's astronaut (a real face, so the detector finds
and aligns it every frame), scaled to ``--width`` and shifted a little from frame to frame as a
webcam's would be.

* **throughput**: the page's pacing (at most two frames in flight), frames answered per second;
  the two pacings are measured in alternating rounds (``--rounds``), so a change in the machine's
  load falls on both;
* **latency**: one frame at a time, from sending its message to having its triplane (the server's
  decode, face detection and alignment, encode, and both transfers over loopback), median and 90th
  percentile; ``server`` is the part inside the server (from the message's arrival to its answer);
* **stages**: the same steps called directly, median milliseconds each;
* **bytes**: the JPEG frame sent, the triplane message received (float16 planes and its header).

Prints a markdown table.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import statistics
import struct
import subprocess
import sys
import time
from typing import Any

import numpy as np


def frames(width: int, n: int) -> list[bytes]:
    """``n`` JPEG frames of the astronaut at ``width`` x 3/4 ``width``, each shifted a few pixels."""
    from PIL import Image
    from skimage.data import astronaut

    face = Image.fromarray(astronaut()).crop((40, 0, 440, 300))  # 4:3, the face in the middle
    out = []
    for i in range(n):
        dx, dy = (3 * np.sin(i / 3), 2 * np.cos(i / 4))
        img = face.transform(face.size, Image.AFFINE, (1, 0, dx, 0, 1, dy), resample=Image.BILINEAR)
        img = img.resize((width, width * 3 // 4), Image.BILINEAR)
        buffer = io.BytesIO()
        img.save(buffer, format="JPEG", quality=80)
        out.append(buffer.getvalue())
    return out


def stages(state, jpegs: list[bytes]) -> dict[str, float]:
    """Median milliseconds of each step, called directly (no server)."""
    from lp3d.serve.lifting import LiveSession

    session = LiveSession()
    lifter = state.lifter
    align, encode, cpu = [], [], []
    for data in jpegs:
        t0, c0 = time.perf_counter(), time.process_time()
        face, info = lifter.align_frame(data, session)
        t1 = time.perf_counter()
        lifter.encode(face)
        t2, c2 = time.perf_counter(), time.process_time()
        align.append(1000 * (t1 - t0))
        encode.append(1000 * (t2 - t1))
        cpu.append(1000 * (c2 - c0))
    return {
        "decode + detect + align": statistics.median(align),
        "encode": statistics.median(encode),
        "cpu": statistics.median(cpu),
        "faces found": (session.frames - session.no_face) / session.frames,
    }


def stream(port: int, jpegs: list[bytes], seconds: float, in_flight: int) -> dict[str, Any]:
    """Stream ``jpegs`` (looped) for ``seconds`` with at most ``in_flight`` frames unanswered: the
    frames answered, the seconds, and each answer's latency, server time and size."""
    from websockets.sync.client import connect

    from lp3d.serve.lifting import MESSAGE_MAGIC

    sent: dict[int, float] = {}
    latency, server, sizes = [], [], []
    answered = 0
    with connect(f"ws://127.0.0.1:{port}/ws/live", max_size=None) as ws:
        i, t_end = 0, time.perf_counter() + seconds
        t_start = time.perf_counter()
        dropped = 0  # frames the server reports overtaken: never answered
        while time.perf_counter() < t_end or len(sent) > dropped:
            while len(sent) - dropped < in_flight and time.perf_counter() < t_end:
                sent[i] = time.perf_counter()
                ws.send(struct.pack("<I", i) + jpegs[i % len(jpegs)])
                i += 1
            message = ws.recv(timeout=60)
            now = time.perf_counter()
            assert message[:4] == MESSAGE_MAGIC, message[:200]
            (n,) = struct.unpack_from("<I", message, 4)
            header = json.loads(message[8 : 8 + n])
            latency.append(1000 * (now - sent.pop(header["frame"])))
            server.append(header["timings_ms"]["server"])
            sizes.append(len(message))
            answered += 1
            dropped = header["dropped"]
        elapsed = time.perf_counter() - t_start
    return {"answered": answered, "elapsed": elapsed, "latency": latency, "server": server, "sizes": sizes}


def summary(runs: list[dict[str, Any]]) -> dict[str, float]:
    """The rounds of one pacing together."""
    latency = sorted(x for r in runs for x in r["latency"])
    return {
        "fps": sum(r["answered"] for r in runs) / sum(r["elapsed"] for r in runs),
        "latency_ms": statistics.median(latency),
        "latency_p90_ms": latency[int(0.9 * (len(latency) - 1))],
        "server_ms": statistics.median(x for r in runs for x in r["server"]),
        "message_bytes": statistics.median(x for r in runs for x in r["sizes"]),
    }


def start_server() -> tuple[subprocess.Popen, int]:
    """``lp3d serve --port 0`` and the port it printed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "lp3d.cli", "serve", "--port", "0"], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    for line in proc.stdout:
        if found := re.search(r"open http://127\.0\.0\.1:(\d+)/", line):
            return proc, int(found.group(1))
    raise RuntimeError(f"lp3d serve exited ({proc.wait()}) without printing its address")


def main(argv: list[str] | None = None) -> int:
    from lp3d.lift.inference import DEFAULT_MODEL, load_encoder
    from lp3d.serve import make_state

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="seconds of each streamed measurement")
    p.add_argument("--rounds", type=int, default=5, help="alternations of the two pacings")
    p.add_argument("--width", type=int, default=320, help="frame width (the page sends 320)")
    args = p.parse_args(argv)

    encoder = load_encoder(DEFAULT_MODEL)
    state = make_state(encoder, refine=False)
    jpegs = frames(args.width, 24)
    stage = stages(state, jpegs * 2)
    proc, port = start_server()
    runs: dict[int, list[dict[str, Any]]] = {1: [], 2: []}
    try:
        stream(port, jpegs, 2.0, 2)  # warm up
        for _ in range(args.rounds):  # alternated, so that a change of the machine's load hits both
            for in_flight in (2, 1):
                runs[in_flight].append(stream(port, jpegs, args.seconds / args.rounds, in_flight))
        paced, single = summary(runs[2]), summary(runs[1])
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    w, h = args.width, args.width * 3 // 4
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (other jobs share them)")
    print(
        f"model: {encoder.description}; frames {w}x{h} JPEG q80, {statistics.median(map(len, jpegs)):.0f} B"
    )
    print()
    rows = [
        (
            "server-side align + encode, two frames in flight (the page's pacing)",
            f"{paced['fps']:.1f} frames/s",
        ),
        ("one frame at a time", f"{single['fps']:.1f} frames/s"),
        (
            "frame-to-triplane latency, one at a time: median (p90)",
            f"{single['latency_ms']:.0f} ms ({single['latency_p90_ms']:.0f} ms)",
        ),
        ("of which inside the server", f"{single['server_ms']:.0f} ms"),
        (
            "latency at the page's pacing: median (p90)",
            f"{paced['latency_ms']:.0f} ms ({paced['latency_p90_ms']:.0f} ms)",
        ),
        ("stage: decode + detect + align (direct call)", f"{stage['decode + detect + align']:.1f} ms"),
        ("stage: encode (direct call)", f"{stage['encode']:.1f} ms"),
        ("stage: CPU time of both, all threads (direct call)", f"{stage['cpu']:.1f} ms"),
        ("frames with the face found", f"{100 * stage['faces found']:.0f} %"),
        ("bytes per frame to the server (JPEG)", f"{statistics.median(map(len, jpegs)) / 1024:.1f} KiB"),
        ("bytes per frame back (float16 planes + header)", f"{paced['message_bytes'] / 1024:.1f} KiB"),
    ]
    print("| measure | value |")
    print("|---|---:|")
    for name, value in rows:
        print(f"| {name} | {value} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
