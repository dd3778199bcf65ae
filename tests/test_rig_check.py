"""A stereo rig's extrinsics judged against its images (``calib.rig_check``), on the real Hamlyn pair written as a
version-2 session by the documented script: the right rig passes; its inverse (the usual hand-written mistake: a
stereo calibration's R, T given as T_cam0_cam[1]) and millimetres read as metres are each named, with the fix."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from lapreco_hil.calib.rig_check import check_rig, check_rig_pair
from lapreco_hil.geometry import inv_T
from lapreco_hil.sessions import Session

from test_real_stereo_pair import HAMLYN, _documented_v2_script


@pytest.fixture(scope="module")
def hamlyn_v2(tmp_path_factory):
    out = tmp_path_factory.mktemp("rig") / "hamlyn-v2"
    script = out.parent / "hamlyn_session.py"
    script.write_text(_documented_v2_script())
    subprocess.run([sys.executable, str(script), str(HAMLYN), str(out)], check=True)
    session = Session(out)
    frame = session.frame(0)
    return session.meta.rig, frame.image, frame.views[0]


def test_the_calibrated_rig_fits_its_images(hamlyn_v2):
    rig, left, right = hamlyn_v2
    (fit,) = check_rig(rig, (left, right))
    assert fit.problem is None
    assert fit.matches >= 100 and fit.fitting_share > 0.8 and fit.in_front_share > 0.95
    assert 0.05 < fit.median_depth_m < 0.08  # the phantom at 58-84 mm (docs/session-format.md)


def test_an_inverted_rig_is_named_with_its_fix(hamlyn_v2):
    rig, left, right = hamlyn_v2
    inverted = replace(rig, T_cam0_cam=(np.eye(4), inv_T(rig.T_cam0_cam[1])))
    fit = check_rig_pair(inverted, 1, left, right)
    # its epipolar lines are nearly the same (a rotation near the identity): only the depths' sign tells
    assert fit.fitting_share > 0.8 and fit.in_front_share < 0.2 and fit.inverse_in_front_share > 0.95
    assert fit.problem.startswith("rig.T_cam0_cam[1] looks inverted") and "give their inverse" in fit.problem


def test_a_baseline_in_the_wrong_unit_is_named(hamlyn_v2):
    rig, left, right = hamlyn_v2
    T = rig.T_cam0_cam[1].copy()
    T[:3, 3] *= 1000.0  # millimetres read as metres
    fit = check_rig_pair(replace(rig, T_cam0_cam=(np.eye(4), T)), 1, left, right)
    assert fit.median_depth_m > 10 and "units.length" in fit.problem


def test_extrinsics_that_do_not_fit_are_named(hamlyn_v2):
    rig, left, right = hamlyn_v2
    T = rig.T_cam0_cam[1].copy()
    T[:3, 3] = [0.0, 0.0055, 0.0]  # the right camera put above the left
    fit = check_rig_pair(replace(rig, T_cam0_cam=(np.eye(4), T)), 1, left, right)
    assert fit.fitting_share < 0.5 and fit.free_fitting_share > 0.8
    assert fit.problem.startswith("rig.T_cam0_cam[1] does not fit the images")
