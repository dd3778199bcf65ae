"""Third-party console output routed into Python logging, so that the app's own one-line error is the only
line a failure prints: OpenCV's WARN/ERROR lines, VTK's output window and logger, and the canopen library's
SDO error records. Called once at app start
(the CLI does); with ``lapreco -v`` what VTK said shows as INFO records."""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)
vtk_log = logging.getLogger("lapreco_hil.vtk")


def route_third_party_output() -> None:
    import cv2

    # OpenCV's own logger writes straight to the console; what it reports the app reports as its own errors
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    # canopen logs each aborted SDO transfer at ERROR; the driver turns the abort into its own one-line error (a
    # probe of absent nodes printed four library lines before it), so its records show with -v only, as INFO does
    logging.getLogger("canopen").setLevel(logging.CRITICAL if log.getEffectiveLevel() > logging.INFO
                                          else logging.NOTSET)
    _route_vtk()


def _route_vtk() -> None:
    import pyvista  # noqa: F401  (on import it installs its own output window, logging at WARNING; replaced here)
    from vtkmodules.vtkCommonCore import VTK_STRING, vtkCommand, vtkLogger, vtkOutputWindow

    # vtkLogger writes WARN|/ERR| lines to stderr by itself; the output window below carries the same messages
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    window = vtkOutputWindow()
    window.SetDisplayModeToNever()  # the observers below are where its messages go

    def forward(_obj, event: str, message: str | None = None) -> None:
        if message:
            vtk_log.info("VTK %s: %s", event.removesuffix("Event").lower(), message.strip())

    forward.CallDataType = VTK_STRING
    for event in (vtkCommand.ErrorEvent, vtkCommand.WarningEvent, vtkCommand.TextEvent):
        window.AddObserver(event, forward)
    vtkOutputWindow.SetInstance(window)
