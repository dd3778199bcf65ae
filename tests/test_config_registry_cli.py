import numpy as np
import pytest

from lapreco_hil.cli.main import main
from lapreco_hil.config import PipelineConfig, config_from_dict, load_config
from lapreco_hil.errors import ConfigError
from lapreco_hil.registry import DeviceContext, open_grabber, open_robot


def test_config_defaults_and_overrides(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[mapper]\nwindow_keyframes = 5\n[prior]\njoint_sigma = [0.001, 0.001, 0.0001, 0.001]\n")
    cfg = load_config(path)
    assert cfg.mapper.window_keyframes == 5
    assert cfg.prior.joint_sigma == (0.001, 0.001, 0.0001, 0.001)
    assert cfg.tracker == PipelineConfig().tracker


@pytest.mark.parametrize("text,match", [
    ("[mapper]\nbogus = 1\n", r"\[mapper\] bogus: unknown key"),
    ("[mapper]\nwindow_keyframes = 'many'\n", r"\[mapper\] window_keyframes = 'many': must be a whole number >= 2"),
    ("[mapper]\nwindow_keyframes = -3\n", r"\[mapper\] window_keyframes = -3: must be >= 2"),
    ("[mapper]\nwindow_keyframes = 1\n", r"\[mapper\] window_keyframes = 1: must be >= 2"),
    ("[tracker]\nmax_lk_error = nan\n", r"\[tracker\] max_lk_error = nan: must be a finite number > 0"),
    ("[tracker]\nquality_level = 1.5\n", r"\[tracker\] quality_level = 1.5: must be > 0 and <= 1"),
    ("[prior]\nfloor_rot_sigma_rad = 0\n", r"\[prior\] floor_rot_sigma_rad = 0: must be > 0"),
    ("[prior]\njoint_sigma = [0.1, -1]\n", r"\[prior\] joint_sigma = \[0.1, -1\]: each value must be >= 0"),
    ("[runtime]\ncapture_queue = 0\n", r"\[runtime\] capture_queue = 0: must be >= 1"),
    ("[runtime]\nsurface_period_s = inf\n", r"\[runtime\] surface_period_s = inf: must be a finite number > 0"),
    ("[tracker]\nmax_features = 10\n\xff\n", "not UTF-8"),
    ("[mapper\n", "not valid TOML"),
    ("mapper = 3\n", "'mapper' must be a table"),
])
def test_malformed_config_names_file_and_key(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_bytes(text.encode("latin-1"))  # \xff: a byte that is not UTF-8
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_every_numeric_config_field_declares_its_range_and_the_defaults_are_in_it():
    import dataclasses
    import typing

    defaults = PipelineConfig()
    for section in dataclasses.fields(defaults):
        sub = getattr(defaults, section.name)
        hints = typing.get_type_hints(type(sub))
        for f in dataclasses.fields(sub):
            if hints[f.name] in (int, float) or typing.get_origin(hints[f.name]) is tuple:
                assert "range" in f.metadata, f"[{section.name}] {f.name} declares no range (use ranged())"
    # every default, written out and loaded back, passes its own range check
    import json

    assert config_from_dict(json.loads(json.dumps(dataclasses.asdict(defaults)))) == defaults  # (lists, as TOML)


def test_unknown_url_scheme_lists_the_known_ones():
    with pytest.raises(ConfigError, match=r"unknown scheme 'bogus' \(known: canopen, replay, serial, sim\)"):
        open_robot("bogus://x", DeviceContext())
    with pytest.raises(ConfigError, match="no scheme"):
        open_grabber("skull", DeviceContext())


def test_sim_devices_with_one_name_share_one_world(warp_cpu):
    ctx = DeviceContext(device=warp_cpu)
    robot = open_robot("sim://apple?width=160&height=120", ctx)
    grabber = open_grabber("sim://apple?width=160&height=120&frames=2", ctx)
    assert robot.world is grabber.world
    assert open_robot("sim://apple", DeviceContext(device=warp_cpu)).world is not robot.world
    with pytest.raises(ConfigError, match="conflicts"):
        open_grabber("sim://apple?width=320", ctx)
    with robot, grabber:
        samples = robot.read()
        assert len(samples) <= 1  # no simulated time has passed yet
        frame = grabber.read()
        samples += robot.read()
    # the robot's samples cover the frame's capture time, so the pose can be interpolated there
    assert samples[0].t_ns <= frame.t_ns < samples[-1].t_ns
    assert np.all(np.diff([s.t_ns for s in samples]) > 0)


@pytest.mark.parametrize("args,match", [
    (["demo", "--scene", "nope"], "unknown scene 'nope' (known: apple, board, liver, skull, uterus)"),
    (["demo", "--out", "/proc/forbidden/out"], "cannot write to output folder '/proc/forbidden/out'"),
])
def test_cli_bad_input_is_one_clear_line(tmp_path, capsys, args, match):
    if "--out" not in args:
        args = args + ["--out", str(tmp_path / "o")]
    assert main(args + ["--no-progress", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"lapreco: error: {match}"] or (len(err) == 1 and match in err[0])
    assert "Traceback" not in "".join(err)


def test_cli_malformed_config(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[tracker]\nmax_features = -\n")
    assert main(["demo", "--config", str(cfg), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cfg) in err[0] and "not valid TOML" in err[0]


def test_cli_rejects_bad_resolution(capsys):
    assert main(["demo", "--resolution", "big"]) == 2
    assert capsys.readouterr().err.splitlines() == ["lapreco: error: --resolution: 'big' must look like 640x480"]


def test_tracker_auto_is_warp_on_a_gpu_and_opencv_on_a_cpu():
    from lapreco_hil.frontend import resolve_tracker

    assert resolve_tracker("auto", "cuda:0") == "warp"
    assert resolve_tracker("auto", "cpu") == "opencv"
    assert resolve_tracker("warp", "cpu") == "warp"
    with pytest.raises(ConfigError, match="unknown tracker 'klt'"):
        resolve_tracker("klt", "cpu")
