"""One progress-bar helper for every long-running command (rich)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn


@contextmanager
def progress_bar(
    description: str, total: int, enabled: bool = True, completed: int = 0
) -> Iterator[Callable[[int], None]]:
    """Context manager yielding ``advance(n=1)``; draws a bar on stderr when ``enabled``,
    starting at ``completed`` of ``total`` (work done before, e.g. resumed rounds)."""
    if not enabled:
        yield lambda n=1: None
        return
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task(description, total=total, completed=completed)
        yield lambda n=1: bar.advance(task, n)
