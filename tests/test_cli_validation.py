"""Every bad number is refused before any work: on the command line by the option's type (exit 2, one line
``lapreco: error: <option>: ...``, no traceback, no output folder), in a configuration file by the field's
declared range (the file, the section and the key)."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from lapreco_hil.cli import args as cli_args
from lapreco_hil.cli.main import build_parser, main

BAD_NUMBERS = [
    (["demo", "--seed", "-1"], "--seed", ">= 0"),
    (["demo", "--seed", "4294967296"], "--seed", "<= 2147483647"),
    (["demo", "--fps", "0"], "--fps", "> 0"),
    (["demo", "--fps", "-25"], "--fps", "> 0"),
    (["demo", "--fps", "nan"], "--fps", "finite"),
    (["demo", "--fps", "inf"], "--fps", "finite"),
    (["demo", "--sim-speed", "0"], "--sim-speed", "> 0"),
    (["demo", "--frames", "0"], "--frames", ">= 1"),
    (["demo", "--frames", "2.5"], "--frames", "whole number"),
    (["demo", "--view-every", "-1"], "--view-every", ">= 0"),
    (["demo", "--resolution", "10x10"], "--resolution", "64..8192"),
    (["sim-record", "--out", "s", "--fps", "0"], "--fps", "> 0"),
    (["sim-record", "--out", "s", "--sim-speed", "-0.1"], "--sim-speed", "> 0"),
    (["sim-record", "--out", "s", "--kinematics-offset-ms", "nan"], "--kinematics-offset-ms", "finite"),
    (["record", "--robot", "sim://skull", "--grabber", "sim://skull", "--out", "s", "--seconds", "0"],
     "--seconds", "> 0"),
    (["run", "--robot", "sim://skull", "--grabber", "sim://skull", "--out", "o", "--seconds", "0"],
     "--seconds", "> 0"),
    (["run", "--robot", "sim://skull", "--grabber", "sim://skull", "--out", "o", "--view-every", "nan"],
     "--view-every", "finite"),
    (["replay", "s", "--out", "o", "--time-offset-ms", "inf"], "--time-offset-ms", "finite"),
    (["evaluate", "o", "--truth", "t.ply", "--coverage-mm", "0"], "--coverage-mm", "> 0"),
    (["devices", "--probe", "sim://skull", "--seconds", "0"], "--seconds", "> 0"),
    (["bench", "pipeline", "--seconds", "0"], "--seconds", "> 0"),
    (["bench", "pipeline", "--fps", "-60"], "--fps", "> 0"),
    (["bench", "pipeline", "--features", "0"], "--features", ">= 1"),
    (["bench", "soak", "--minutes", "0"], "--minutes", "> 0"),
    (["bench", "soak", "--sample-s", "nan"], "--sample-s", "finite"),
    (["bench", "robot", "--rate", "100", "0"], "--rate", "> 0"),
    (["bench", "robot", "--seconds", "-5"], "--seconds", "> 0"),
    (["bench", "frontend", "--frames", "0"], "--frames", ">= 1"),
    (["bench", "ba", "--repeats", "0"], "--repeats", ">= 1"),
    (["bench", "session", "--frames", "-1"], "--frames", ">= 1"),
]


@pytest.mark.parametrize("argv,option,range_text", BAD_NUMBERS, ids=[" ".join(a) for a, _, _ in BAD_NUMBERS])
def test_a_bad_number_is_one_line_naming_the_option(argv, option, range_text, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"lapreco: error: {option}: "), lines[0]
    assert range_text in lines[0]
    assert not out and not any(tmp_path.iterdir())  # nothing ran, nothing was written


def test_every_numeric_option_has_a_ranged_type():
    """No raw int/float type and no number without a type, on every subcommand (the calibration parsers are
    the calibration module's)."""

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    if name != "calibrate":
                        yield from walk(sub, path + [name])
            elif action.option_strings and action.nargs != 0:
                yield path, action

    checked = 0
    typed = set()
    for path, action in walk(build_parser(), []):
        where = f"{' '.join(path)} {action.option_strings[0]}"
        if action.type is not None:
            typed.add(where)
        assert action.type not in (int, float), f"{where}: raw {action.type.__name__} (use lapreco_hil.cli.args)"
        default = action.default[0] if isinstance(action.default, list) else action.default
        if isinstance(default, (int, float)) and not isinstance(default, bool):
            assert action.type is not None, f"{where}: a number without a type"
            checked += 1
    assert checked >= 20
    # numbers whose default is None (none given: no limit, or the device's own default) are typed as well
    assert {"record --seconds", "record --frames", "run --seconds", "replay --time-offset-ms", "bench pipeline --fps",
            "bench pipeline --features", "bench pipeline --resolution"} <= typed


def test_argument_types_accept_their_ranges_and_refuse_the_rest():
    assert cli_args.positive("1e-3") == 1e-3 and cli_args.non_negative("0") == 0.0
    assert cli_args.finite("-12.5") == -12.5 and cli_args.seed("0") == 0 and cli_args.positive_int("3") == 3
    for parse, text in ((cli_args.positive, "0"), (cli_args.positive, "-inf"), (cli_args.non_negative, "-1e-9"),
                        (cli_args.finite, "nan"), (cli_args.seed, "-1"), (cli_args.positive_int, "1.0"),
                        (cli_args.positive, "fast")):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


def test_argparse_own_errors_are_one_line_too(capsys):
    assert main(["demo", "--robot-link", "usb"]) == 2
    assert main(["replay"]) == 2
    assert main(["frobnicate"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3 and all(line.startswith("lapreco: error: ") for line in lines)
    assert lines[0].startswith("lapreco: error: --robot-link: invalid choice: 'usb'")
    assert "usage:" not in "".join(lines)


def test_a_bad_config_number_is_one_line_naming_file_section_and_key(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "config.toml").write_text("[mapper]\nwindow_keyframes = 0\n")
    assert main(["demo", "--config", "config.toml", "--out", "o", "--device", "cpu", "--no-progress"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "lapreco: error: config.toml: [mapper] window_keyframes = 0: must be >= 2"]
    assert not (tmp_path / "o").exists()


def test_the_installed_command_prints_no_traceback():
    """Through a real process: stderr holds the one line and nothing else (no usage, no traceback, no third-party
    output)."""
    proc = subprocess.run([sys.executable, "-m", "lapreco_hil.cli.main", "demo", "--fps", "0"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == ["lapreco: error: --fps: 0 is out of range: must be > 0"]
    assert proc.stdout == ""


NOISY = ("import cv2; cv2.VideoCapture('/dev/video99', cv2.CAP_V4L2)\n"
         "from vtkmodules.vtkCommonCore import vtkOutputWindow\n"
         "vtkOutputWindow.GetInstance().DisplayErrorText('vtk says boom')\n")


@pytest.mark.parametrize("routed", [False, True])
def test_opencv_and_vtk_console_output_goes_to_the_log(routed):
    """OpenCV's WARN lines and VTK's output window reach the console only through logging (INFO, shown with
    -v); without the routing both print straight to stderr."""
    setup = ("import logging; logging.basicConfig(level=logging.INFO, format='%(name)s: %(message)s')\n"
             "from lapreco_hil.app.noise import route_third_party_output; route_third_party_output()\n"
             if routed else "")
    proc = subprocess.run([sys.executable, "-c", setup + NOISY], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    if routed:
        assert "WARN" not in proc.stderr and "VIDEOIO" not in proc.stderr
        assert proc.stderr.strip().splitlines() == ["lapreco_hil.vtk: VTK error: vtk says boom"]
    else:
        assert "VIDEOIO" in proc.stderr and "vtk says boom" in proc.stderr
