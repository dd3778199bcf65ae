"""``lookup.positions``: ids found among ids (a local window's observations among its landmarks, a frame's tracks
among the map's depths) as a sorted search finds them, by its table over a short span of ids and by the search
where the span is long, ids lie below the known ones, or the ids are not integers."""

import numpy as np
import pytest

from lapreco_hil.lookup import ID_TABLE_MIN, ID_TABLE_SPAN, positions


@pytest.fixture
def rng():
    return np.random.default_rng(11)


@pytest.mark.parametrize("keys_sorted", [True, False])
def test_positions_finds_each_id_where_a_sorted_search_does_by_its_table_and_by_the_search(rng, keys_sorted):
    known = np.unique(rng.integers(1000, 5000, 800))
    keys = known if keys_sorted else rng.permutation(known)
    short = rng.integers(1000, 6000, 3000)  # some above the known ids, many absent
    wide = np.concatenate([short, [1000 + (ID_TABLE_SPAN + 1) * 10 ** 6 + ID_TABLE_MIN]])  # beyond any table
    below = np.concatenate([short, [3]])
    for ids in (short, wide, below, known[::-1].copy(), short.astype(float)):
        at, found = positions(keys, ids, keys_sorted=keys_sorted)
        expected = np.isin(ids, known)
        np.testing.assert_array_equal(found, expected)
        np.testing.assert_array_equal(keys[at[found]], ids[found])
        assert at.min() >= 0 and at.max() < len(keys)
