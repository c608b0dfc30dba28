"""Stopping a training at a step boundary on Ctrl-C or SIGTERM (what `timeout` and job
schedulers send), so that its checkpoint is written and ``--resume`` continues it."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

#: the signals a training turns into a stop at the next step boundary
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_requests() -> Iterator[list[int]]:
    """Within the block, SIGINT and SIGTERM append their number to the yielded list instead of
    interrupting (the loop checks it between steps); the previous handlers are restored after.
    Outside the main thread, where Python cannot set handlers, the list stays empty."""
    stop: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {s: signal.signal(s, lambda signum, _: stop.append(signum)) for s in STOP_SIGNALS}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
