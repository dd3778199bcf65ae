"""Ids found among ids: a frame's tracks among the map's depths, a window's observations among its landmarks, a
stereo view's tracks among the previous frame's. Track ids grow with a run, and the ids looked up at once are
recent ones, so a table indexed by id over their span is usually small, and cheaper than sorting."""

from __future__ import annotations

import numpy as np

# a table indexed by id is used where the ids span at most ID_TABLE_SPAN times their count plus ID_TABLE_MIN (a
# table of a few MB costs less than sorting), else a sorted search
ID_TABLE_SPAN = 32
ID_TABLE_MIN = 65536


def positions(keys: np.ndarray, queries: np.ndarray, keys_sorted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Where each of ``queries`` is in ``keys`` (distinct, not empty; ``keys_sorted``: ascending already):
    (positions in ``keys``, valid indices but meaningless where not found; found)."""
    keys, queries = np.asarray(keys), np.asarray(queries)
    if len(queries) and np.issubdtype(keys.dtype, np.integer) and np.issubdtype(queries.dtype, np.integer):
        low = int(min(keys.min(), queries.min()))
        span = int(max(keys.max(), queries.max())) - low + 1
        if span <= ID_TABLE_SPAN * (len(keys) + len(queries)) + ID_TABLE_MIN:
            table = np.full(span, -1, np.int64)
            table[keys - low] = np.arange(len(keys))
            at = table[queries - low]
            found = at >= 0
            return np.maximum(at, 0), found
    order = None if keys_sorted else np.argsort(keys)
    sorted_keys = keys if order is None else keys[order]
    by_query = np.argsort(queries)  # (sorted queries: the search walks the sorted keys once, not at random)
    at = np.empty(len(queries), np.int64)
    at[by_query] = np.minimum(np.searchsorted(sorted_keys, queries[by_query]), len(keys) - 1)
    found = sorted_keys[at] == queries
    return (at if order is None else order[at]), found
