"""Lemniscate (figure-eight) beneath a hovering leader, every condition on the same seeds.

    python -m experiments.lemniscate [--conditions baseline,oracle] [--seeds 5] [--quick]

Paper section 5: Alpha hovers at 2.5 m; Bravo flies a figure-eight whose crossing
point lies directly beneath Alpha, so it passes through the wake twice per period.
"""

from __future__ import annotations

from dataclasses import dataclass

from controllers.references import Lemniscate
from experiments.common import arg, parse_args, setup_logging
from experiments.tracking import TrackingArgs, run_tracking

PERIOD = 20.0  # s, one figure-eight


@dataclass(frozen=True)
class LemniscateArgs(TrackingArgs):
    half_length: float = arg(1.0, "half extent of the figure-eight along x, m")
    half_width: float = arg(0.5, "half extent along y, m")


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(LemniscateArgs, "lemniscate", argv, __doc__)
    if args.quick:
        args = type(args)(**{**args.__dict__, "seeds": min(args.seeds, 1), "duration": args.duration or 2.0})

    def reference(center, n_worlds):
        return Lemniscate(center, half_length=args.half_length, half_width=args.half_width, period=PERIOD, n_worlds=n_worlds)

    return run_tracking("lemniscate", args, reference, PERIOD)


if __name__ == "__main__":
    main()
