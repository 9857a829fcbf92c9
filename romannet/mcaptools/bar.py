"""The mcap tools' progress bar: romannet.progress.Progress placed by the fraction of the file(s) done, its
rate counted in what the tool handles (transitions, messages, frames, files)."""

from __future__ import annotations

from typing import TextIO

from romannet.progress import FIELD_SEP, Progress


class ProgressBar(Progress):
    """Context manager: `with ProgressBar("feed", "transitions") as bar: bar.update(0.42, "file 3/12", count=n)`."""

    def __init__(self, label: str, unit: str = "", stream: TextIO | None = None, log_every_s: float = 10.0):
        super().__init__(label, total=1.0, unit=unit, stream=stream, log_every_s=log_every_s, redraw_s=0.1,
                         counts_done=False, initial=0.0)

    def update(self, fraction: float, detail: str = "", *, count: float | None = None,  # type: ignore[override]
               force: bool = False) -> None:
        """fraction of the work done; detail: ' | '-separated fields, the most important first."""
        super().update(fraction, detail.split(FIELD_SEP) if detail else [], count=count, force=force)
