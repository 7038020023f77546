"""The terminal progress of a run: a rich progress bar, or nothing."""

from __future__ import annotations

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.progress import Progress as RichProgress

__all__ = ["Progress"]


class Progress:
    """A rich progress bar (frame i/N, sim time, steps/s, ETA), or nothing.

    A context manager; with ``enabled=False`` every method does nothing.
    """

    def __init__(self, enabled: bool, console=None):
        self.enabled = enabled
        self._console = console
        self._progress = None
        self._sim_task = None
        self._render_task = None

    def __enter__(self) -> "Progress":
        if self.enabled:
            console = self._console or Console(stderr=True)
            self._progress = RichProgress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=console,
                transient=False,
            )
            self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)
            self._progress = None

    def print(self, message: str) -> None:
        if self._progress is not None:
            self._progress.console.print(message)

    def start_sim(self, done: int, total: int, t: float) -> None:
        if self._progress is not None:
            self._sim_task = self._progress.add_task(
                "simulating", total=total, completed=done, info=f"t = {t:.3f} s"
            )

    def update_sim(self, frame: int, t: float, steps_per_s: float) -> None:
        if self._progress is not None and self._sim_task is not None:
            self._progress.update(
                self._sim_task, completed=frame, info=f"t = {t:.3f} s  {steps_per_s:,.0f} steps/s"
            )

    def start_render(self, total: int, label: str = "rendering preview") -> None:
        if self._progress is not None:
            self._render_task = self._progress.add_task(label, total=total, info="")

    def advance_render(self) -> None:
        if self._progress is not None and self._render_task is not None:
            self._progress.advance(self._render_task)
