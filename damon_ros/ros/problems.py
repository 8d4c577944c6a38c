"""One log line per kind of bad input, then a throttled count: nodes never flood their log."""

from __future__ import annotations

import re
import time
from collections.abc import Callable


class Problem(str):
    """A one-line problem message that carries its ``kind``: the name of the check that
    failed (``marker.size_too_large``), which is what `ProblemLog` throttles on.

    A ``str``, so that code which logs, joins or compares messages keeps working.
    """

    kind: str

    def __new__(cls, message: str, kind: str) -> Problem:
        obj = super().__new__(cls, message)
        obj.kind = str(kind)
        return obj


class ProblemError(ValueError):
    """A refused input; ``problem`` is its `Problem` (message and kind)."""

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.problem = Problem(message, kind)

    @property
    def kind(self) -> str:
        return self.problem.kind


def problem_of(exc: BaseException, default_kind: str) -> Problem:
    """The `Problem` an exception describes (``default_kind`` for a plain one)."""
    if isinstance(exc, ProblemError):
        return exc.problem
    return Problem(str(exc), default_kind)


class ProblemLog:
    """One log line per kind of problem, then at most one per ``every_s`` with a count.

    rclpy's ``throttle_duration_sec`` throttles per call site, so two different problems at
    one site would hide each other. Here the key is the problem's *kind*: the check that
    failed (`Problem.kind`, or ``kind=``), so a 100 m marker and a size-0 one are two
    problems with two first lines even though their messages differ only in digits, while
    one problem repeating with new numbers in its text is one stream, logged once per
    ``every_s`` with the count of the repeats left out. A message without a kind falls back
    to its text with the numbers blanked.

    ``log`` is one severity of one rclpy logger object: rclpy ties a severity to each call
    site per logger object, and every ProblemLog logs from the same line here, so two
    ProblemLogs of different severities need two logger objects (`rclpy.logging.get_logger`
    with the node logger's name gives a second one).
    """

    def __init__(self, log: Callable[[str], None], every_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self.every_s = float(every_s)
        self._clock = clock
        self._seen: dict[str, tuple[float, int]] = {}  # key -> (last logged, suppressed)

    @staticmethod
    def key(message: str, kind: str | None = None) -> str:
        kind = kind or getattr(message, "kind", None)
        return f"kind:{kind}" if kind else re.sub(r"\d+(\.\d+)?", "#", message)

    def report(self, message: str, kind: str | None = None) -> bool:
        """Log ``message`` unless its kind was logged within ``every_s``; True if logged."""
        key, now = self.key(message, kind), self._clock()
        last = self._seen.get(key)
        if last is not None and now - last[0] < self.every_s:
            self._seen[key] = (last[0], last[1] + 1)
            return False
        suppressed = 0 if last is None else last[1]
        self._log(str(message) if not suppressed else f"{message} ({suppressed} more since)")
        self._seen[key] = (now, 0)
        return True

    def suppressed(self, kind: str) -> int:
        """Repeats of ``kind`` not logged since its last line (for tests and summaries)."""
        return self._seen.get(f"kind:{kind}", (0.0, 0))[1]
