"""Transect: back and forth along y at x = 0.2 m beneath a hovering leader.

    python -m experiments.transect [--conditions baseline,oracle] [--seeds 5] [--quick]

Paper section 5: Alpha hovers at 2.5 m, Bravo 0.6 m below it flies one
back-and-forth pass parallel to the y axis at x = 0.2 m.
"""

from __future__ import annotations

from dataclasses import dataclass

from controllers.references import Transect
from experiments.common import arg, parse_args, setup_logging
from experiments.tracking import TrackingArgs, run_tracking

PERIOD = 12.0  # s, one back-and-forth


@dataclass(frozen=True)
class TransectArgs(TrackingArgs):
    x_offset: float = arg(0.2, "lateral offset of the transect line from the leader, m")
    half_length: float = arg(1.2, "half length of the transect along y, m")


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(TransectArgs, "transect", argv, __doc__)
    if args.quick:
        args = type(args)(**{**args.__dict__, "seeds": min(args.seeds, 1), "duration": args.duration or 2.0})

    def reference(center, n_worlds):
        return Transect(center, x_offset=args.x_offset, half_length=args.half_length, period=PERIOD, n_worlds=n_worlds)

    return run_tracking("transect", args, reference, PERIOD)


if __name__ == "__main__":
    main()
