"""Progress bars on stderr for long runs and batches (tqdm), silent where nobody watches."""

from __future__ import annotations

import sys
from typing import Any


class ProgressBar:
    """A tqdm progress bar on stderr, or nothing: None shows one only on a terminal and only once the work has
    lasted a second (short runs stay silent), True always, False never."""

    def __init__(self, progress: bool | None, total: float, unit: str, desc: str, *, seconds: bool = False):
        self.bar = None
        self.done: float = 0
        if progress is False or (progress is None and not is_terminal(sys.stderr)):
            return  # nothing to show: not even tqdm's import on the way into a run
        from tqdm.auto import tqdm

        self.bar = tqdm(
            total=total,
            unit=unit,
            desc=desc,
            disable=None if progress is None else False,
            delay=1.0 if progress is None else 0.0,
            leave=progress is True,
            file=sys.stderr,
            dynamic_ncols=True,
            # simulated time is a float: show it rounded, not as 1.8900000000000001/3.0
            bar_format="{desc}: {percentage:3.0f}%|{bar}| t = {n:.4g}/{total:.4g} s [{elapsed}<{remaining}]"
            if seconds
            else None,
        )

    @property
    def active(self) -> bool:
        return self.bar is not None and not self.bar.disable

    def reset(self, total: int, unit: str) -> None:
        if self.bar is not None:
            self.bar.unit = unit
            self.bar.reset(total=total)
            self.done = 0

    def update(self, n: float) -> None:
        if self.bar is not None and n:
            self.bar.update(n)
            self.done += n

    def update_to(self, value: float) -> None:
        """Advance the bar to `value` (not beyond: a value below the current one is ignored)."""
        if value > self.done:
            self.update(value - self.done)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def is_terminal(stream: Any) -> bool:
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, OSError, ValueError):  # closed or replaced streams
        return False
