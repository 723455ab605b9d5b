"""The tests train as the experiments do: with torch's portable kernels (`downwash.train`), asked
for here, before any test runs torch, so that what a test trains has the same bits on every CPU."""

from downwash_core.numerics import request_portable_torch

request_portable_torch()


def restamp(payload: dict) -> dict:
    """A checkpoint payload edited on purpose, with its content digest made to match again, so that a test
    reaches the checks behind the digest's (a writer that stamps what it writes, wrong or not)."""
    import torch

    from downwash.checkpoint import content_digest

    state = payload.get("state_dict")
    if (isinstance(payload.get("meta_json"), str) and isinstance(state, dict)
            and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items())):
        payload["content_sha256"] = content_digest(payload["meta_json"], state)
    return payload
