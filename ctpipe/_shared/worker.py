"""The loop a worker process of :class:`ctpipe.execution.ProcessPool` runs.

Started as ``python -c "...serve(R, W)"`` with two pipe ends: tasks arrive on ``R``, replies leave on ``W``, each a
pickle behind its length (8 bytes, little-endian). A task is ``(fn, args)``; the reply ``(True, fn(*args),
warnings)``, or ``(False, exception, warnings)`` where it raised (an exception that cannot be pickled goes back as a
``RuntimeError`` holding its traceback), or ``(None, error, [])`` where the task itself could not be unpickled here;
``warnings`` lists the ``(message, category)`` of those the task raised, each once, which the parent raises again under
its own filters. The loop ends when the parent closes ``R`` (or dies: the same
end of file), so no worker outlives the run that started it.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import traceback
import warnings

_LENGTH = struct.Struct("<Q")


def send(stream, payload: bytes) -> None:
    """Write one framed message and flush it."""
    stream.write(_LENGTH.pack(len(payload)))
    stream.write(payload)
    stream.flush()


def receive(stream) -> bytes:
    """Read one framed message; ``EOFError`` where the other end closed its pipe."""
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        raise EOFError("the pipe closed")
    size, = _LENGTH.unpack(head)
    payload = stream.read(size)
    if len(payload) < size:
        raise EOFError("the pipe closed mid-message")
    return payload


def serve(read_fd: int, write_fd: int) -> None:
    """Run tasks from ``read_fd`` until it closes, each reply to ``write_fd``."""
    # Ctrl-C in a terminal reaches the whole process group: the parent decides, and ends its workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with os.fdopen(read_fd, "rb") as inbox, os.fdopen(write_fd, "wb") as outbox:
        while True:
            try:
                task = receive(inbox)
            except EOFError:
                return
            try:
                fn, args = pickle.loads(task)
            except Exception as exc:   # not the task's error: a class this process cannot import, say
                send(outbox, pickle.dumps((None, RuntimeError(f"{type(exc).__name__}: {exc}"), [])))
                continue
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")   # the parent's filters decide, as for a task on its threads
                try:
                    reply = (True, fn(*args))
                except Exception as exc:   # the task's own error: the parent raises it
                    reply = (False, exc)
            # Each warning once: a numpy warning raised per element would otherwise come back thousands of times.
            raised = list(dict.fromkeys((str(w.message), w.category) for w in caught))
            try:
                payload = pickle.dumps(reply + (raised,), protocol=pickle.HIGHEST_PROTOCOL)
            except Exception:
                text = "".join(traceback.format_exception(reply[1])) if not reply[0] else traceback.format_exc()
                failure = RuntimeError(f"a worker process's reply could not be sent back:\n{text}")
                payload = pickle.dumps((False, failure, []))
            send(outbox, payload)
