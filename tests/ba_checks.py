"""Checks shared by the tests of the Schur solver's camera-system solves (banded, dense on the host or the device)."""

import numpy as np
import pytest


def assert_same_answer(dense, banded, p, device: str = "cpu"):
    """Poses and well-seen landmarks to round-off, the same labels. (A landmark left with one weighted view is
    held along its ray by the damping alone: round-off moves it.) On a GPU, whose atomics sum in a different order
    run to run, LM's last step may be taken or not (the stop is a relative decrease of 1e-5): within 1e-9 there."""
    gpu = device.startswith("cuda")
    np.testing.assert_allclose(banded.poses, dense.poses, rtol=0, atol=1e-9 if gpu else 1e-11)
    views = np.bincount(p.obs_point[dense.stats["inlier_obs"]], minlength=len(p.points))
    np.testing.assert_allclose(banded.points[views >= 2], dense.points[views >= 2], rtol=0,
                               atol=1e-8 if gpu else 1e-10)
    assert np.array_equal(banded.stats["inlier_obs"], dense.stats["inlier_obs"])
    assert banded.final_error == pytest.approx(dense.final_error, rel=1e-8 if gpu else 1e-10)
    if not gpu:
        assert [st["iterations"] for st in banded.stats["stages"]] == [st["iterations"]
                                                                       for st in dense.stats["stages"]]
