"""Transect: back and forth along y at x = 0.2 m beneath a hovering leader, every condition on the same seeds.

    python -m experiments.transect [--conditions baseline,oracle] [--seeds 5] [--quick]

The `transect` entry of the table in `experiments.tracking`, which holds the logic.
"""

from experiments.tracking import main

if __name__ == "__main__":
    main("transect")
