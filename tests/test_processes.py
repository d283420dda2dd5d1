"""A function in a second process: its result, its exception, a process that dies, and stopping it."""

from __future__ import annotations

import os
import time

import pytest

from diamond_sss.utils.processes import BackgroundCall, usable_cores


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


def test_usable_cores_is_positive():
    assert 1 <= usable_cores() <= (os.cpu_count() or 1)
