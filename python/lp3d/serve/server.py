"""Running ``lp3d serve``'s app: its shared state from a loaded encoder, and uvicorn on a socket
bound before it starts (so that ``--port 0`` can print the port it got), in this thread or another."""

from __future__ import annotations

import secrets
import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from lp3d.lift.loaded import LoadedEncoder
from lp3d.render.settings import RenderSettings

__all__ = ["WORKERS", "Server", "make_state", "missing_extra"]

#: Threads that lift photos and live frames for every client together (each frame also uses ONNX
#: Runtime's own threads).
WORKERS = 2
#: What the ``serve`` extra installs: module names.
EXTRA_MODULES = ("starlette", "uvicorn", "websockets")


def missing_extra() -> str | None:
    """None when the ``serve`` extra is installed, else the one-line error that says how."""
    import importlib.util

    missing = [m for m in EXTRA_MODULES if importlib.util.find_spec(m) is None]
    if not missing:
        return None
    names = ", ".join(missing)
    return f"lp3d serve needs {names}: pip install 'lp3d[serve]' (or pip install {' '.join(EXTRA_MODULES)})"


def make_state(
    encoder: LoadedEncoder,
    *,
    token: str | None = None,
    loopback: bool = True,
    settings: RenderSettings | None = None,
    refine: bool = True,
) -> Any:
    """The app's :class:`~lp3d.serve.app.ServeState` for ``encoder``; ``token`` None needs none."""
    from lp3d.serve.app import ServeState
    from lp3d.serve.jobs import RefineJobs, torch_available
    from lp3d.serve.lifting import Lifter
    from lp3d.serve.page import build_serve_page

    page, script_hash = build_serve_page(encoder, settings=settings, token_required=token is not None)
    lifter = Lifter(encoder)
    lifter.warm_up()
    state = ServeState(
        lifter=lifter,
        page=page,
        script_hash=script_hash,
        token=token,
        loopback=loopback,
        workers=ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="lp3d-serve"),
    )
    if refine and torch_available():
        state.refine = RefineJobs(state.photos, encoder.package)
    return state


def new_token() -> str:
    return secrets.token_urlsafe(24)


class Server:
    """uvicorn serving ``state``'s app on ``host``:``port`` (0: any free port, see :attr:`port`)."""

    def __init__(self, state: Any, host: str, port: int) -> None:
        import uvicorn

        from lp3d.serve.app import create_app

        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((host, port))
        self.sock.listen(128)  # connections made once the address is printed wait for uvicorn
        self.host, self.port = host, self.sock.getsockname()[1]
        self.state = state
        config = uvicorn.Config(
            create_app(state),
            log_level="warning",
            access_log=False,
            lifespan="off",
            ws_max_size=state.live_limits.max_message_bytes,
            # Deflating 768 KiB of float16 planes per frame costs more time than loopback saves.
            ws_per_message_deflate=False,
            limit_concurrency=64,
        )
        self.server = uvicorn.Server(config)
        self.thread: threading.Thread | None = None

    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        query = f"?token={self.state.token}" if self.state.token is not None else ""
        return f"http://{host}:{self.port}/{query}"

    def run(self) -> None:
        """Serve until interrupted (Ctrl-C), in this thread."""
        self.server.run(sockets=[self.sock])

    def start(self) -> Server:
        """Serve on a thread of its own; returns once the server listens."""
        self.thread = threading.Thread(target=self.run, name="lp3d-serve", daemon=True)
        self.thread.start()
        while not self.server.started:
            if not self.thread.is_alive():
                raise RuntimeError("the server stopped while starting")
            threading.Event().wait(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self.thread is not None:
            self.thread.join(timeout=10)
        self.sock.close()
        self.state.workers.shutdown(wait=False, cancel_futures=True)
