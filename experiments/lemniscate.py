"""Lemniscate (figure-eight) beneath a hovering leader, every condition on the same seeds.

    python -m experiments.lemniscate [--conditions baseline,oracle] [--seeds 5] [--quick]

The `lemniscate` entry of the table in `experiments.tracking`, which holds the logic.
"""

from experiments.tracking import main

if __name__ == "__main__":
    main("lemniscate")
