"""A function run in a second (spawned) process: its result, its exception, or an error if the process dies."""

from __future__ import annotations

import multiprocessing
import os
import pickle
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the platform has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _call_and_send(connection: Connection, function: Callable[..., Any], args: tuple) -> None:
    """In the child: send ``("ok", function(*args))``, or ``("error", exception)`` (its traceback as text when the
    exception cannot be pickled)."""
    try:
        outcome = ("ok", function(*args))
    except Exception as exc:  # noqa: BLE001 - any failure is handed to the parent, which raises it
        outcome = ("error", exc)
    try:
        connection.send(outcome)
    except (pickle.PicklingError, TypeError, AttributeError):  # an unpicklable result or exception
        connection.send(("error", RuntimeError(traceback.format_exc())))
    finally:
        connection.close()


class BackgroundCall:
    """``function(*args)`` started in a spawned daemon process (``function`` and ``args`` must pickle).

    :meth:`result` waits for it: the return value, the child's exception raised here, or a ``RuntimeError``
    naming ``label`` and the exit code when the process ends without an answer (killed, e.g. for memory).
    :meth:`stop` terminates it if it still runs (a no-op after :meth:`result`).
    """

    def __init__(self, function: Callable[..., Any], args: tuple, label: str) -> None:
        context = multiprocessing.get_context("spawn")
        self.label = label
        self._receive, send = context.Pipe(duplex=False)
        self.process = context.Process(target=_call_and_send, args=(send, function, args), daemon=True)
        self.process.start()
        send.close()

    def result(self) -> Any:
        try:
            status, value = self._receive.recv()  # end of file: the child closed its end without sending
        except EOFError:
            self.process.join()
            raise RuntimeError(f"{self.label}: its process ended without a result "
                               f"(exit code {self.process.exitcode}; killed for lack of memory?)") from None
        self.process.join()
        if status == "error":
            raise value
        return value

    def stop(self) -> None:
        if self.process.is_alive():
            self.process.terminate()
        self.process.join()
