"""The samples a registered field is fitted to: labelled real-flight samples, each a follower with one leader.

    states = pair_states(read)                        # read: (ref, FlightLog) of real flights

Samples (`pair_states`): `downwash.real_logs.flights.labelled_samples`' (contacts, crashes and their
margins dropped), each with one leader: the vehicle above the follower (by more than WAKE_DEPTH[0])
laterally nearest to it, since every field's wake is a column below its leader, so the lateral offset
decides whether the follower is in it; with none above, the nearest other vehicle, whose wake the fields
put at (or near) zero there, which keeps a fit honest about where there is no wake. Samples under two or
more vehicles (``LS2S``, ...) are dropped: their force is two wakes' sum, which one leader cannot give.
Each vehicle's kind comes from its flight's meta ("kinds", or a Neural-Swarm frame through
`FRAME_KINDS`). `PairStates` carries the data's digest (`PairStates.data_digest`: another selection or
subset, another digest), which a fit records. `downwash.field_fit` fits fields to them (and re-exports
everything here).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.geometry import quat_to_mat
from downwash_core.io import to_json
from downwash_core.vehicles import get_vehicle
from downwash.labels import DEFAULT_POLYORDER, DEFAULT_WINDOW
from downwash.real_logs.flights import (CONTACT_DISTANCE, CONTACT_MARGIN_S, REST_HEIGHT, WAKE_DEPTH,
                                        labelled_samples)

__all__ = ["PairStates", "FRAME_KINDS", "pair_states"]

FRAME_KINDS = {"small": "crazyflie_2_1", "large": "crazyflie_large"}  # Neural-Swarm frames without meta "kinds"
# each per-sample array of PairStates and its shape after the sample axis
_ARRAYS = {"p_a": (3,), "v_a": (3,), "R_a": (3, 3), "p_b": (3,), "v_b": (3,), "y": (3,), "kind_a": (), "kind_b": (),
           "flight": (), "row": (), "vehicle": (), "types": ()}


@dataclass(frozen=True, eq=False)
class PairStates:
    """N labelled samples of real flights, each a follower with one leader (module doc); world frame, z up."""

    p_a: np.ndarray  # (N, 3) m, the leader's position (estimate)
    v_a: np.ndarray  # (N, 3) m/s, the leader's velocity
    R_a: np.ndarray  # (N, 3, 3) the leader's body-to-world rotation
    p_b: np.ndarray  # (N, 3) m, the follower's position
    v_b: np.ndarray  # (N, 3) m/s, the follower's velocity
    y: np.ndarray  # (N, 3) m/s^2, the label f = a - u on the follower
    kind_a: np.ndarray  # (N,) int, the leader's kind: an index into `kinds`
    kind_b: np.ndarray  # (N,) int, the follower's kind
    flight: np.ndarray  # (N,) int, an index into `flight_names` and `flight_digests`
    row: np.ndarray  # (N,) int, the row in the flight's log
    vehicle: np.ndarray  # (N,) int, the follower in its flight
    types: np.ndarray  # (N,) str, `downwash.real_logs.flights.interaction_types`
    kinds: tuple[str, ...]  # registered vehicle kinds
    flight_names: tuple[str, ...]
    flight_digests: tuple[str, ...]  # SHA-256 (hex) over each flight's source digests
    selection: Mapping[str, Any] = dataclasses.field(default_factory=dict)  # how the samples were chosen
    source: str = ""  # one line: where they come from

    def __post_init__(self) -> None:
        n = np.shape(self.y)[0] if np.ndim(self.y) == 2 else -1
        for name, trail in _ARRAYS.items():
            a = np.asarray(getattr(self, name))
            if a.shape != (n, *trail):
                raise ConfigError(f"PairStates.{name}: expected shape {(max(n, 0), *trail)}, got {a.shape}")
            object.__setattr__(self, name, a)
        if len(self.flight_digests) != len(self.flight_names):
            raise ConfigError(f"PairStates: {len(self.flight_names)} flight names, {len(self.flight_digests)} digests")
        for name, top in (("kind_a", len(self.kinds)), ("kind_b", len(self.kinds)), ("flight", len(self.flight_names))):
            if getattr(self, name).size and not 0 <= getattr(self, name).min() <= getattr(self, name).max() < top:
                raise ConfigError(f"PairStates.{name}: indices must lie in [0, {top})")

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def n_flights(self) -> int:
        return int(np.unique(self.flight).size)

    @functools.cached_property
    def data_digest(self) -> str:
        """SHA-256 (hex) over the flights' digests (of ``meta["source"]["files"][i]["sha256"]``), the selection
        and the samples' (flight, row, vehicle)."""
        keys = np.stack([self.flight, self.row, self.vehicle]).astype("<i8").tobytes()
        text = to_json({"flights": list(self.flight_digests), "selection": dict(self.selection),
                        "samples": hashlib.sha256(keys).hexdigest()})
        return hashlib.sha256(text.encode()).hexdigest()

    @functools.cached_property
    def groups(self) -> list[tuple[Any, Any, np.ndarray, tuple[np.ndarray, ...]]]:
        """(leader kind, follower kind, indices, their (p_a, v_a, R_a, p_b, v_b)) per pair of kinds present:
        gathered once, as a fit evaluates its field many times."""
        code, K = self.kind_a * len(self.kinds) + self.kind_b, len(self.kinds)
        return [(get_vehicle(self.kinds[c // K]), get_vehicle(self.kinds[c % K]), i,
                 tuple(a[i] for a in (self.p_a, self.v_a, self.R_a, self.p_b, self.v_b)))
                for c in np.unique(code) for i in (np.flatnonzero(code == c),)]

    def subset(self, index: np.ndarray) -> "PairStates":
        """The samples at an index array or boolean mask (names, digests and selection kept)."""
        return dataclasses.replace(self, **{name: getattr(self, name)[index] for name in _ARRAYS})


def _flight_digest(ref: Any, flight: Any) -> str:
    """SHA-256 over one flight's source files' digests; DataError for a flight that has none."""
    source = flight.meta.get("source")
    digests = [f.get("sha256") for f in (source.get("files") or ())] if isinstance(source, dict) else []
    if not digests or not all(isinstance(d, str) for d in digests):
        raise DataError(f"{getattr(ref, 'name', ref)}: no source digests (meta source.files[].sha256): "
                        "pair_states reads real flights")
    return hashlib.sha256("\n".join(digests).encode()).hexdigest()


def _flight_kinds(ref: Any, flight: Any) -> list[str]:
    """Each vehicle's registered kind: meta "kinds", else its Neural-Swarm frame through FRAME_KINDS."""
    kinds = flight.meta.get("kinds") or [FRAME_KINDS.get(f) for f in flight.meta.get("frames") or ()]
    if len(kinds) != flight.n_vehicles or not all(kinds):
        raise DataError(f"{getattr(ref, 'name', ref)}: no vehicle kinds (meta 'kinds', or 'frames' of "
                        f"{sorted(FRAME_KINDS)}); got kinds {flight.meta.get('kinds')}, frames {flight.meta.get('frames')}")
    return [get_vehicle(k).name for k in kinds]  # ConfigError naming the registered kinds


def _leaders(pos: np.ndarray, follower: np.ndarray) -> np.ndarray:
    """(n,) the leader of each sample (module doc): pos (n, V, 3) m at its row, follower (n,)."""
    rel = pos - pos[np.arange(len(follower)), follower][:, None, :]  # every vehicle from the follower
    others = np.arange(pos.shape[1]) != follower[:, None]
    above = others & (rel[..., 2] > WAKE_DEPTH[0])
    lateral = np.where(above, np.linalg.norm(rel[..., :2], axis=-1), np.inf)
    dist = np.where(others, np.linalg.norm(rel, axis=-1), np.inf)
    return np.where(above.any(axis=1), lateral.argmin(axis=1), dist.argmin(axis=1))


def _flight_part(ref: Any, flight: Any, data: Any, types: np.ndarray, sel: np.ndarray, kinds: dict) -> dict:
    """The arrays of one flight's samples `sel` of `data` (labelled_samples'); kinds numbered in `kinds`."""
    rows = np.minimum(np.searchsorted(flight["t"], data.t[sel]), len(flight["t"]) - 1)
    if not np.array_equal(flight["t"][rows], data.t[sel]):  # labelled_samples keeps the log's times exactly
        raise DataError(f"{getattr(ref, 'name', ref)}: labelled sample times are not the log's rows")
    follower, n = data.vehicle[sel], np.arange(sel.size)
    pos = flight["pos_est"][rows].astype(np.float64)
    lead = _leaders(pos, follower)
    index = np.array([kinds.setdefault(kind, len(kinds)) for kind in _flight_kinds(ref, flight)])
    return {"p_a": pos[n, lead], "v_a": flight["vel_est"][rows, lead].astype(np.float64),
            "R_a": quat_to_mat(flight["quat_est"][rows, lead].astype(np.float64)), "p_b": pos[n, follower],
            "v_b": data.v_b[sel], "y": data.y[sel], "kind_a": index[lead], "kind_b": index[follower],
            "row": rows, "vehicle": follower, "types": types[sel]}


def pair_states(flights: Sequence[tuple[Any, Any]], stride: int = 2, source: str | None = None) -> PairStates:
    """The pair samples (module doc) of real flights, (ref, FlightLog) as `read_flights` gives them.
    DataError when no sample has another vehicle, or a flight has no source digests or vehicle kinds;
    ConfigError for a kind that is not registered."""
    data, types = labelled_samples(flights, stride)
    over = np.char.partition(types.astype(str), "2")[:, 0]  # who flies over: "LS" of "LS2S", "none", "Ge"
    keep = data.mask[:, 0] & (np.isin(over, ("none", "Ge")) | (np.char.str_len(over) <= 1))
    order = {getattr(ref, "name", str(ref)): k for k, (ref, _) in enumerate(flights)}
    kinds, parts = {}, []  # kind name -> its index; each flight's arrays
    for fid in np.unique(data.flight[keep]):  # a data set's flight ids are not the list's indices: its sources are
        k = order[data.sources[fid]]
        part = _flight_part(*flights[k], data, types, np.flatnonzero(keep & (data.flight == fid)), kinds)
        parts.append({**part, "flight": np.full(len(part["y"]), k)})
    if not parts:
        raise DataError(f"no labelled sample with another vehicle in the {len(flights)} flights given")
    selection = {"labels": "downwash.real_logs.flights.labelled_samples", "stride": stride, "window": DEFAULT_WINDOW,
                 "polyorder": DEFAULT_POLYORDER, "rest_height": REST_HEIGHT, "contact_distance": CONTACT_DISTANCE,
                 "contact_margin_s": CONTACT_MARGIN_S, "leader": f"laterally nearest above by > {WAKE_DEPTH[0]} m, "
                 "else nearest", "dropped": "samples under two or more vehicles; vehicles flying alone"}
    fmt = sorted({str((f.meta.get("source") or {}).get("format")) for _, f in flights})
    return PairStates(**{name: np.concatenate([p[name] for p in parts]) for name in _ARRAYS}, kinds=tuple(kinds),
                      flight_names=tuple(getattr(r, "name", str(r)) for r, _ in flights),
                      flight_digests=tuple(_flight_digest(r, f) for r, f in flights), selection=selection,
                      source=source or f"{len(flights)} real flights ({', '.join(fmt)})")
