"""What devices this machine can see: serial ports, SocketCAN interfaces, V4L2 video devices."""

from __future__ import annotations


def discover() -> dict[str, list[str]]:
    from .grabber.v4l2 import video_devices
    from .robot.canopen402 import can_interfaces
    from .robot.dynamixel import serial_ports

    return {"serial": serial_ports(), "can": can_interfaces(), "v4l2": video_devices()}


def format_devices(found: dict[str, list[str]]) -> str:
    examples = {"serial": "serial://{}?baud=1000000&ids=1,2,3,4", "can": "canopen://socketcan/{}?nodes=1-4",
                "v4l2": "v4l2://{}?width=1920&height=1080&fps=60"}
    titles = {"serial": "serial ports (Dynamixel robots)", "can": "SocketCAN interfaces (CANopen robots)",
              "v4l2": "V4L2 video devices (frame grabbers)"}
    lines = []
    for kind in ("serial", "can", "v4l2"):
        lines.append(f"{titles[kind]}:")
        if not found[kind]:
            lines.append("  none")
        for dev in found[kind]:
            lines.append(f"  {dev:<20} {examples[kind].format(dev)}")
    lines.append("simulated: sim://skull | sim://liver | sim://apple (robot and grabber; link=serial|canopen on the "
                 "robot goes through a device emulator); recorded: replay://SESSION")
    return "\n".join(lines)
