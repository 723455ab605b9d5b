"""One name -> reference factory, for experiments and envs alike.

`make_reference("lemniscate", center, n_worlds, half_length=0.8)` builds the named
reference around `center` (the point the follower flies about: for the paper's
experiments, the point `separation` below the leader). Unknown names and unknown
shape parameters raise ConfigError naming what is allowed.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_core.validate import choice
from downwash_trajectories.base import Reference
from downwash_trajectories.primitives import Circle, Hover, Lemniscate, Line, Transect

__all__ = ["REFERENCES", "REFERENCE_KWARGS", "make_reference"]

# name -> the shape parameters it accepts (keywords of its class; hover: `offset`, (3,) m from center)
REFERENCE_KWARGS = MappingProxyType({
    "hover": ("offset",),
    "lemniscate": ("half_length", "half_width", "period"),
    "transect": ("x_offset", "half_length", "period"),
    "line": ("velocity", "duration"),
    "circle": ("radius", "speed", "phase"),
})
REFERENCES = tuple(REFERENCE_KWARGS)


def make_reference(name: str, center: ArrayLike, n_worlds: int | None = None, **kwargs: Any) -> Reference:
    """The reference `name` around `center` ((3,) or (W, 3) m, world frame) for `n_worlds` worlds
    (for "line", `center` is the start; default velocity (1, 0, 0) m/s).

    kwargs: the shape parameters of REFERENCE_KWARGS[name] (each a float or (W,) array).
    """
    choice("reference", name, REFERENCES)
    unknown = sorted(set(kwargs) - set(REFERENCE_KWARGS[name]))
    if unknown:
        raise ConfigError(
            f"reference_kwargs: unknown {unknown} for reference {name!r}; allowed: {', '.join(REFERENCE_KWARGS[name])}"
        )
    if name == "hover":
        offset = np.array(kwargs.get("offset", (0.0, 0.0, 0.0)), dtype=float)
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise ConfigError(f"reference_kwargs['offset']: expected 3 finite numbers (m), got {kwargs.get('offset')!r}")
        return Hover(np.asarray(center, dtype=float) + offset, n_worlds=n_worlds)
    if name == "line":
        return Line(center, kwargs.get("velocity", (1.0, 0.0, 0.0)), kwargs.get("duration", 10.0), n_worlds=n_worlds)
    cls = {"lemniscate": Lemniscate, "transect": Transect, "circle": Circle}[name]
    return cls(center, n_worlds=n_worlds, **kwargs)
