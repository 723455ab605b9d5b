"""The tests train as the experiments do: with torch's portable kernels (`downwash.train`), asked
for here, before any test runs torch, so that what a test trains has the same bits on every CPU."""

from downwash_core.numerics import request_portable_torch

request_portable_torch()
