"""One log line per kind of bad input, then a throttled count: nodes never flood their log."""

from __future__ import annotations

import re
import time
from collections.abc import Callable


class ProblemLog:
    """One log line per kind of problem, then at most one per ``every_s`` with a count.

    rclpy's ``throttle_duration_sec`` throttles per call site, so two different problems at
    one site would hide each other; here the key is the message with its numbers blanked, so
    "encoding 'bgra8'" and "size 320x240" are separate problems, while the same problem with
    a new stamp in its text is not.
    """

    def __init__(self, log: Callable[[str], None], every_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self.every_s = float(every_s)
        self._clock = clock
        self._seen: dict[str, tuple[float, int]] = {}  # key -> (last logged, suppressed)

    @staticmethod
    def key(message: str) -> str:
        return re.sub(r"\d+(\.\d+)?", "#", message)

    def report(self, message: str) -> bool:
        """Log ``message`` unless its kind was logged within ``every_s``; True if logged."""
        key, now = self.key(message), self._clock()
        last = self._seen.get(key)
        if last is not None and now - last[0] < self.every_s:
            self._seen[key] = (last[0], last[1] + 1)
            return False
        suppressed = 0 if last is None else last[1]
        self._log(message if not suppressed else f"{message} ({suppressed} more since)")
        self._seen[key] = (now, 0)
        return True
