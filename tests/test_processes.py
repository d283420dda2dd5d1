"""A function in a second process: its result, its exception, a process that dies, and stopping it."""

from __future__ import annotations

import os
import signal
import time

import pytest

from diamond_sss.utils.processes import (
    BackgroundCall,
    ChildProgress,
    idle_cpu_cores,
    threads_for_idle,
    usable_cores,
)


def test_the_result_comes_back():
    assert BackgroundCall(sum, ([1, 2, 3],), label="a sum").result() == 6


def test_the_childs_exception_is_raised_here():
    with pytest.raises(ValueError, match="invalid literal for int"):
        BackgroundCall(int, ("not a number",), label="a parse").result()


def test_a_process_that_dies_is_an_error_naming_it_and_its_exit_code():
    with pytest.raises(RuntimeError, match=r"the dense reconstruction \(out\): .*exit code 3"):
        BackgroundCall(os._exit, (3,), label="the dense reconstruction (out)").result()


def test_stop_terminates_a_running_call():
    call = BackgroundCall(time.sleep, (60,), label="a sleep")
    started = time.perf_counter()
    call.stop()
    assert not call.process.is_alive() and time.perf_counter() - started < 30


def test_usable_cores_are_the_affinity_masks_not_the_machines():
    allowed = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(allowed)})  # this process may run on one core, whatever the machine has
        assert usable_cores() == 1
    finally:
        os.sched_setaffinity(0, allowed)
    assert usable_cores() == len(allowed)


def test_a_progress_bar_here_follows_the_steps_the_child_reports():
    with ChildProgress(total=7, description="child", interval=0.05) as progress:
        BackgroundCall(progress.reporter, (7,), label="a report").result()  # the child calls reporter(7)
        deadline = time.perf_counter() + 30
        while progress.bar.n != 7 and time.perf_counter() < deadline:  # the polling thread, not close(), shows it
            time.sleep(0.05)
        assert progress.bar.n == 7
    assert progress.close() == 7 and progress.steps == 7


def test_a_step_reporter_ignores_a_training_callbacks_other_arguments():
    with ChildProgress(total=3, description="here") as progress:
        assert progress.reporter(2, "scene", {"loss": 1.0}) is None
    assert progress.steps == 2 and progress.bar.n == 2


def test_a_process_killed_by_a_signal_is_an_error_naming_the_signal():
    call = BackgroundCall(time.sleep, (60,), label="a sleep")
    os.kill(call.process.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match=r"a sleep: .*killed by signal 9"):
        call.result()


def test_idle_cores_are_what_the_other_processes_leave_of_this_ones_cpus(monkeypatch):
    import psutil

    monkeypatch.setattr(psutil, "cpu_percent", lambda interval, percpu: [100.0, 30.0, 0.0, 50.0])
    if hasattr(os, "sched_getaffinity"):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 3})  # cpu 2 is not this process's
    else:
        monkeypatch.setattr(os, "cpu_count", lambda: 3)
    idle, usable = idle_cpu_cores()
    assert usable == 3 and idle == pytest.approx(0.0 + 0.7 + 0.5)


def test_threads_take_the_idle_cores_rounded_and_at_least_one():
    assert [threads_for_idle(idle) for idle in (0.0, 0.4, 1.3, 1.5, 1.6, 2.0, 7.8)] == [1, 1, 1, 2, 2, 2, 8]
