"""Running the demo server: a private temporary workspace, loopback binding, clean shutdown.

Uploaded files, generated samples and every output live in one temporary folder made for
this server (`private_workspace`) and removed when it stops, including on Ctrl-C and
SIGTERM, or by the next server when this one was killed; nothing is written anywhere
else. Gradio is imported only inside `serve`, after its environment is set: it reads
``GRADIO_TEMP_DIR`` (where it keeps uploads) at import time.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from taptr.apps.demo.settings import DEFAULT_HOST, DEFAULT_PORT, MAX_UPLOAD, Limits
from taptr.io.atomic import remove_stale_temporaries

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

logger = logging.getLogger(__name__)

WORKSPACE_PREFIX = "taptr-demo-"
"""Start of the name of each server's temporary folder (``taptr-demo-PID-XXXX.tmp``)."""


@contextlib.contextmanager
def private_workspace() -> Iterator[Path]:
    """A new temporary folder for one server's files, removed on exit.

    Points Gradio's upload cache at ``<workspace>/uploads`` (and matplotlib's cache, which
    Gradio imports when installed, at ``<workspace>/matplotlib``) and turns Gradio's
    analytics off; these settings must be in the environment before Gradio is imported.
    """
    # the pid in the name lets the next server remove what a killed one (SIGKILL) left
    remove_stale_temporaries(Path(tempfile.gettempdir()), WORKSPACE_PREFIX, ".tmp")
    workspace = Path(tempfile.mkdtemp(prefix=f"{WORKSPACE_PREFIX}{os.getpid()}-", suffix=".tmp"))
    keys = ("GRADIO_TEMP_DIR", "GRADIO_ANALYTICS_ENABLED", "MPLCONFIGDIR")
    previous = {key: os.environ.get(key) for key in keys}
    os.environ["GRADIO_TEMP_DIR"] = str(workspace / "uploads")
    os.environ["GRADIO_ANALYTICS_ENABLED"] = "False"
    # Gradio imports matplotlib when it is installed, which would write its font cache
    # into the user's home; keep it with the server's other files
    os.environ.setdefault("MPLCONFIGDIR", str(workspace / "matplotlib"))
    if "gradio" in sys.modules:
        logger.warning(
            "gradio was imported before the demo's workspace was set: uploads go to its own "
            "cache folder, not to %s",
            workspace,
        )
    try:
        yield workspace
    finally:
        shutil.rmtree(workspace, ignore_errors=True)
        for key, value in previous.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def serve(
    predictor: Predictor,
    workspace: Path,
    *,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    limits: Limits | None = None,
    model_name: str = "",
    block: bool = True,
) -> Any:
    """Builds the page and serves it until interrupted (Ctrl-C or SIGTERM).

    Args:
        predictor: the tracker shared by all users.
        workspace: the folder from `private_workspace`.
        host: interface to bind; 127.0.0.1 keeps the demo on this machine.
        port: TCP port.
        limits: frame, resolution and point limits.
        model_name: shown on the page and stored with the tracks.
        block: wait until the server is interrupted; False returns the running
            ``gr.Blocks`` at once (call its ``close()``), for use from Python.

    Returns:
        The ``gr.Blocks`` app, closed when ``block`` is True.

    Raises:
        OSError: the port is taken.
    """
    from taptr.apps.demo.app import build_app

    limits = limits or Limits()
    demo = build_app(predictor, workspace=workspace, limits=limits, model_name=model_name)
    # One job at a time: a second tracking run would only halve the speed of both.
    demo.queue(default_concurrency_limit=1, max_size=32)
    if block and threading.current_thread() is threading.main_thread():
        # Gradio shuts down cleanly on KeyboardInterrupt; make SIGTERM take the same path
        # so the workspace is removed when a service manager stops the demo.
        signal.signal(signal.SIGTERM, _interrupt)
    demo.launch(
        server_name=host,
        server_port=port,
        # we wait ourselves: Gradio's own wait prints "Keyboard interruption in main
        # thread" on every stop, SIGTERM included
        prevent_thread_lock=True,
        allowed_paths=[str(workspace)],
        max_file_size=MAX_UPLOAD,
        ssr_mode=False,  # server-side rendering would start a Node.js process
        show_error=True,
        quiet=True,
        # The run-history page can copy users' runs to a Hugging Face bucket: keep them here.
        run_history=False,
    )
    if block:
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass
        finally:
            demo.close()
    return demo


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt
