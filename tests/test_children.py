"""`process_age_s`: what the sweep's and its engine processes' start-up lines measure from."""

from __future__ import annotations

import subprocess
import sys
import time

from vabench.children import process_age_s


def test_a_process_age_counts_from_its_start():
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        time.sleep(1.0)
        age = process_age_s(child.pid)
        assert age is not None and 0.9 <= age <= 5.0, age
        mine = process_age_s()
        assert mine is not None and mine > age  # this test's process started before its child
    finally:
        child.kill()
        child.wait()


def test_a_process_that_is_gone_has_no_age():
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    assert process_age_s(child.pid) is None
