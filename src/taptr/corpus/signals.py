"""Which signal stopped a corpus job, even when Ray lost it on the way.

The command line raises its own exception from its SIGTERM handler (``Terminated``, a
KeyboardInterrupt, exit status 143) and Ctrl-C raises KeyboardInterrupt (130). When the
signal arrives while the driver waits in ``ray.wait`` or ``ray.get``, Ray runs the
handler inside its wait and raises a plain KeyboardInterrupt in place of what the handler
raised, so a SIGTERM would read as Ctrl-C. `remembered_stop` wraps the process's handlers
for the job and keeps what they raised, so that the job stops with that exception.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals that stop a job cleanly."""


class Stop:
    """What the handlers raised in the block, if anything (`remembered_stop`)."""

    def __init__(self) -> None:
        self.raised: BaseException | None = None


@contextlib.contextmanager
def remembered_stop() -> Iterator[Stop]:
    """Wraps the SIGINT and SIGTERM handlers for the block, keeping what they raise.

    A KeyboardInterrupt leaving the block becomes what a handler raised last (Ray's in
    its place, or the handler's own). Only Python handlers are wrapped (the default
    SIGINT handler is one); outside the main thread, where handlers cannot be set,
    nothing is changed.
    """
    stop = Stop()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {number: signal.getsignal(number) for number in STOP_SIGNALS}
    for number, handler in previous.items():
        if callable(handler):
            signal.signal(number, _remembering(handler, stop))
    try:
        yield stop
    except KeyboardInterrupt as caught:
        if stop.raised is None or stop.raised is caught:
            raise
        raise stop.raised from None  # what the process's handler meant (Terminated: 143)
    finally:
        for number, handler in previous.items():
            if callable(handler):
                signal.signal(number, handler)


def _remembering(handler: Any, stop: Stop) -> Any:
    def remember(number: int, frame: FrameType | None) -> None:
        try:
            handler(number, frame)
        except BaseException as error:
            stop.raised = error
            raise

    return remember
