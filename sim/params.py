"""Deprecated: the parameters moved to `core.params`."""

import warnings

from core.params import *  # noqa: F401,F403
from core.params import __all__  # noqa: F401

warnings.warn("sim.params is deprecated; import from core.params instead", DeprecationWarning, stacklevel=2)
