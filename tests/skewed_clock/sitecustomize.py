"""Loaded at start by a test's Python process whose ``PYTHONPATH`` names this directory: its wall clock
(``time.time``, ``time.time_ns``) runs ``FTRAIN_TEST_CLOCK_SKEW`` seconds off, as on a host whose clock drifted.
Monotonic clocks are left alone (each host has its own anyway). libfaketime does this for C code too, but under it
Python's ``time.sleep`` fails (EINVAL) or timed waits stall, so it cannot run ftrain here."""

import os
import time

_SKEW = float(os.environ.get("FTRAIN_TEST_CLOCK_SKEW") or 0)
if _SKEW:
    _time, _time_ns = time.time, time.time_ns
    time.time = lambda: _time() + _SKEW
    time.time_ns = lambda: _time_ns() + int(_SKEW * 1e9)
