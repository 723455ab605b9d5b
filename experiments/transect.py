"""Transect: back and forth along y at x = 0.2 m beneath a hovering leader, every condition on the same seeds.

    python -m experiments.transect [--conditions baseline,oracle] [--seeds 5] [--quick]

The `transect` entry of the table in `experiments.tracking`, which holds the logic.
"""

from typing import Sequence

from experiments.common import run_main, script
from experiments.tracking import main as run_track


def main(argv: Sequence[str] | None = None) -> dict:
    """The transect on the command line (or `argv`); returns its results."""
    return run_track("transect", argv)


cli = script(main)  # the console script (pyproject.toml)

if __name__ == "__main__":
    run_main(main)
