"""What every experiment prints through: its plain tables, its logging and its progress bars."""

from __future__ import annotations

import logging
import sys
from typing import Any, Sequence

__all__ = ["format_table", "OWN_LOGGERS", "setup_logging", "ProgressBar"]


def format_table(rows: Sequence[Sequence[Any]], header: Sequence[str]) -> str:
    """A plain fixed-width table; floats with 4 significant digits."""

    def fmt(x: Any) -> str:
        if isinstance(x, float):
            return f"{x:.4g}"
        return str(x)

    cells = [[fmt(x) for x in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


# the packages whose INFO messages a run shows (other libraries' show from WARNING: PyOpenGL, for one,
# reports at INFO what it did not find when MuJoCo renders through EGL)
OWN_LOGGERS = ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs",
               "experiments", "__main__")


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    for name in OWN_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose else logging.INFO)


class ProgressBar:
    """A tqdm progress bar with rate and ETA on stderr, for `progress(done, total)` callbacks;
    quiet when stderr is not a terminal (CI, logs, pipes). `ProgressBar(label)` is also the
    progress factory the library takes (`downwash.staged.collect(..., progress=ProgressBar)`)."""

    def __init__(self, label: str, unit: str = "it"):
        self.label, self.unit = label, unit
        self._bar: Any = None  # a tqdm bar, made on the first call

    def __call__(self, done: int, total: int) -> None:
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=self.label, unit=self.unit, disable=not sys.stderr.isatty(),
                             dynamic_ncols=True, leave=True)
        self._bar.update(done - self._bar.n)
        if done >= total:
            self._bar.close()
