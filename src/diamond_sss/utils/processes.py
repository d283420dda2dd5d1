"""A function run in a second (spawned) process: its result, its exception, or an error if the process dies; a
progress bar here that follows the steps the second process reports; and the CPU cores this process may use and
those that are idle."""

from __future__ import annotations

import math
import multiprocessing
import os
import pickle
import threading
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from tqdm.auto import tqdm

if TYPE_CHECKING:
    from typing_extensions import Self  # typing.Self from Python 3.11


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the platform has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def idle_cpu_cores(sample_s: float = 0.2) -> tuple[float, int]:
    """``(idle, usable)``: how many of the :func:`usable_cores` no process used over the next ``sample_s`` seconds
    (system-wide busy shares from psutil, ``sum(1 - busy_i)`` over this process's CPUs), while this one waits."""
    import psutil

    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else range(usable_cores())
    busy = psutil.cpu_percent(interval=sample_s, percpu=True)
    return sum(1.0 - busy[i] / 100.0 for i in allowed if i < len(busy)), len(allowed)


def threads_for_idle(idle: float) -> int:
    """Threads for work that should take the idle cores and no more (more threads than free cores slow every job on
    them: oversubscription): ``idle`` rounded to the nearest count, at least 1."""
    return max(1, math.floor(idle + 0.5))


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
    naming ``label`` and the exit code or signal when the process ends without an answer (killed, e.g. for memory).
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
            code = self.process.exitcode
            how = (f"killed by signal {-code} (for lack of memory?)" if code < 0
                   else f"exit code {code}; its error output, if any, is above")
            raise RuntimeError(f"{self.label}: its process ended without a result ({how})") from None
        self.process.join()
        if status == "error":
            raise value
        return value

    def stop(self) -> None:
        if self.process.is_alive():
            self.process.terminate()
        self.process.join()


class StepReporter:
    """Picklable callable for the child: ``reporter(step, *_)`` records the number of steps done (any further
    arguments, e.g. a training step callback's scene and loss terms, are ignored)."""

    def __init__(self, counter: Any) -> None:
        self.counter = counter

    def __call__(self, step: int, *_: Any) -> None:
        self.counter.value = int(step)


class ChildProgress:
    """A tqdm bar in this process that follows the steps a child process reports through :attr:`reporter`.

    Give :attr:`reporter` to the child (e.g. as a training ``on_step`` callback); a thread polls the shared counter
    every ``interval`` seconds. :meth:`close` (or leaving the ``with`` block) stops polling, shows the last count
    and returns it.
    """

    def __init__(self, total: int, description: str, interval: float = 0.5) -> None:
        self.reporter = StepReporter(multiprocessing.get_context("spawn").Value("q", 0))
        self.bar = tqdm(total=total, desc=description, dynamic_ncols=True)
        self._interval = interval
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._follow, daemon=True)
        self._thread.start()

    @property
    def steps(self) -> int:
        """Steps the child has reported so far."""
        return int(self.reporter.counter.value)

    def _show(self) -> None:
        if self.steps != self.bar.n:
            self.bar.n = self.steps
            self.bar.refresh()

    def _follow(self) -> None:
        while not self._stopped.wait(self._interval):
            self._show()

    def close(self) -> int:
        if not self._stopped.is_set():
            self._stopped.set()
            self._thread.join()
            self._show()
            self.bar.close()
        return self.steps

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
