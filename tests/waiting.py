"""Polling helper shared by the CAN tests: wait until a condition holds, or fail saying which."""

import time


def wait_for(predicate, timeout: float = 5.0, what: str = "condition", poll: float = 0.003):
    """The first truthy ``predicate()`` within ``timeout`` seconds, else AssertionError naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout} s")
        time.sleep(poll)
