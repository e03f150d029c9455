"""``lp3d serve``: a local web app: drop a photo or turn on the webcam, and the lifted head is rendered
live in the browser (:mod:`lp3d.serve`, ``docs/serve.md``)."""

from __future__ import annotations

import argparse
import ipaddress
from pathlib import Path

from lp3d.cli.common import CLIError, image_side, int_in, parse_samples, resolve_model, say

HELP = "a local web app: drop a photo or start the webcam, the 3D head follows live in the browser"
DESCRIPTION = (
    "Serve one page that lifts a dropped photo or the webcam's frames with the model and renders the "
    "head in the browser (WebGPU, lp3d's own WGSL). Binds loopback only unless --allow-remote, which "
    "also requires the access token it prints. Nothing is written to disk."
)

#: The port used unless --port says otherwise.
DEFAULT_PORT = 8765


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lp3d.render.settings import RenderSettings

    default = RenderSettings()
    p.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1, this computer only)"
    )
    p.add_argument(
        "--port",
        type=int_in(0, 65535),
        default=DEFAULT_PORT,
        help=f"port (default: {DEFAULT_PORT}; 0: any free port)",
    )
    p.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a --host other than loopback; every request then needs the access token printed at start",
    )
    p.add_argument("--model", type=Path, default=None, help="as for encode")
    p.add_argument("--backend", choices=("onnx", "torch"), default=None, help="as for encode")
    p.add_argument(
        "--resolution",
        type=image_side,
        default=default.resolution,
        help="rays per side of the page's final image (default: %(default)s)",
    )
    p.add_argument(
        "--samples",
        type=parse_samples,
        default=(default.depth_resolution, default.depth_resolution_importance),
        metavar="COARSE+FINE",
        help="samples per ray of the page's final image (default: 48+48)",
    )


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is this computer only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def run(args: argparse.Namespace) -> int:
    from lp3d.serve import missing_extra

    if (why := missing_extra()) is not None:
        raise CLIError(why)
    from lp3d.lift.inference import load_encoder
    from lp3d.render.settings import RenderSettings
    from lp3d.serve import Server, make_state
    from lp3d.serve.server import new_token

    loopback = is_loopback(args.host)
    if not loopback and not args.allow_remote:
        raise CLIError(
            f"--host {args.host} is not loopback: other computers could reach the server; pass "
            "--allow-remote to allow it (every request then needs the access token printed at start)"
        )
    coarse, fine = args.samples
    settings = RenderSettings(
        resolution=args.resolution, depth_resolution=coarse, depth_resolution_importance=fine
    )
    encoder = load_encoder(resolve_model(args.model), args.backend)
    state = make_state(encoder, token=None if loopback else new_token(), loopback=loopback, settings=settings)
    try:
        server = Server(state, "127.0.0.1" if args.host == "localhost" else args.host, args.port)
    except OSError as e:
        raise CLIError(f"cannot listen on {args.host}:{args.port}: {e.strerror or e}") from None
    say(f"model: {encoder.description}")
    if state.refine is None:
        say("refinement is off (PyTorch is not installed)")
    if not loopback:
        say(f"listening on {args.host}, reachable from other computers: the address below holds the token")
        say("webcams and WebGPU need a secure context: from another computer, use HTTPS or an SSH tunnel")
    say(f"lp3d serve: open {server.url()}  (Ctrl-C to stop)")
    server.run()
    return 0
