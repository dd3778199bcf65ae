"""``lapreco emulate dynamixel|canopen|ndi``: arguments for :mod:`lapreco_hil.app.emulate`; prints where to
connect (the pty, or the CAN interface and channel) and the driver URL, one ``key: value`` per line, then runs
until Ctrl-C."""

from __future__ import annotations

import argparse

from lapreco_hil.cli.args import fail, integer, non_negative, positive

VIRTUAL_REFUSED = ("--interface virtual: python-can's virtual bus connects buses inside one process only, so no "
                   "other program could reach this emulator; use --interface socketcan --channel vcan0 (a virtual "
                   "SocketCAN interface), or CANopenDriveChainEmulator in your own Python process")


# each protocol's id range (drivers/robot: DYNAMIXEL_IDS, CANOPEN_NODE_IDS; not imported here: they load the
# robot models, seconds for every lapreco command)
ID_RANGES = {"Dynamixel Protocol 2.0": (0, 252), "CANopen": (1, 127)}


def _ids(protocol: str):
    def parse(text: str) -> tuple[int, ...]:
        from lapreco_hil.registry import id_list_parser

        try:
            return id_list_parser(*ID_RANGES[protocol], protocol)(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"'{text}' {exc}") from None

    parse.__name__ = "id list"
    return parse


def _say(running) -> None:
    for line in running.lines:
        print(line, flush=True)
    print("Ctrl-C to stop", flush=True)


def cmd_emulate(args) -> int:
    from lapreco_hil.app import emulate

    if args.device == "dynamixel":
        running = emulate.start_dynamixel(args.ids, args.baud, args.model, args.motion, args.link_dir,
                                          args.alert or (), args.reply_delay_ms)
    elif args.device == "canopen":
        if args.interface == "virtual":
            return fail(VIRTUAL_REFUSED)
        running = emulate.start_canopen(args.nodes, args.model, args.motion, args.interface, args.channel,
                                        args.fault_bit or ())
    else:
        running = emulate.start_ndi(args.wired, args.passive, args.frame_rate, args.motion, args.link_dir,
                                    args.start_baud, args.start_tracking, args.baud)
    _say(running)
    emulate.serve(running)
    print(f"lapreco emulate {args.device}: stopped", flush=True)
    return 0


def add_parser(sub) -> None:
    emu = sub.add_parser("emulate", help="run one device emulator (Dynamixel chain or NDI tracker on a pty, CiA 402 "
                                         "drives on a SocketCAN interface) for other programs to connect to")
    kinds = emu.add_subparsers(dest="device", required=True)
    motion = dict(choices=("scan", "still"), default="scan",
                  help="scan: the joints (tools) move slowly about the middle of their limits; still: they rest "
                       "there (default: scan)")

    dxl = kinds.add_parser("dynamixel", help="X-series servos on a pseudo-terminal (Protocol 2.0)")
    dxl.add_argument("--ids", type=_ids("Dynamixel Protocol 2.0"), default=(1, 2, 3, 4),
                     help="servo IDs in joint order, e.g. 1,2,3,4 or 1-4 (default: 1-4)")
    dxl.add_argument("--baud", type=integer(ge=1), default=1_000_000,
                     help="the servos' baud rate; a host at any other rate gets no answer (default: 1000000; "
                          "X-series factory setting: 57600)")
    dxl.add_argument("--model", default="ecm", help="robot model (packaged name or URDF): its joints (default: ecm)")
    dxl.add_argument("--motion", **motion)
    dxl.add_argument("--link-dir", default=None, help="folder for the stable name ttyDXL0 (default: a new temporary "
                                                      "folder)")
    dxl.add_argument("--alert", type=integer(ge=0, le=252), action="append", metavar="ID",
                     help="this servo reports a hardware error alert (repeatable)")
    dxl.add_argument("--reply-delay-ms", type=non_negative, default=0.0, help="every reply this late (default: 0)")
    dxl.set_defaults(func=cmd_emulate)

    can = kinds.add_parser("canopen", help="CiA 402 drives on a SocketCAN interface (e.g. a vcan)")
    can.add_argument("--nodes", type=_ids("CANopen"), default=(1, 2, 3, 4),
                     help="node ids in joint order (default: 1-4)")
    can.add_argument("--interface", choices=("socketcan", "virtual"), default="socketcan",
                     help="python-can interface (default: socketcan; virtual is refused: it reaches no other "
                          "process)")
    can.add_argument("--channel", default="vcan0", help="the SocketCAN interface (default: vcan0)")
    can.add_argument("--model", default="ecm", help="robot model (packaged name or URDF): its joints (default: ecm)")
    can.add_argument("--motion", **motion)
    can.add_argument("--fault-bit", type=integer(ge=1, le=127), action="append", metavar="NODE",
                     help="this node's statusword shows a fault (repeatable)")
    can.set_defaults(func=cmd_emulate)

    ndi = kinds.add_parser("ndi", help="an NDI Polaris/Aurora tracker on a pseudo-terminal (Combined API)")
    ndi.add_argument("--wired", type=integer(ge=0, le=16), default=1, help="wired tools, handles 0A, 0B, ... (default: 1)")
    ndi.add_argument("--passive", type=integer(ge=0, le=9), default=0, help="passive tools, each loaded from a .rom (default: 0)")
    ndi.add_argument("--frame-rate", type=positive, default=60.0, help="measurements per second (default: 60)")
    ndi.add_argument("--baud", type=integer(ge=1), default=921600, help="the rate put in the printed URL (default: 921600)")
    ndi.add_argument("--start-baud", type=integer(ge=1), default=9600,
                     help="the rate the device is at when it starts (default: 9600, as after a reset)")
    ndi.add_argument("--start-tracking", action="store_true",
                     help="start in tracking mode, as a device a previous session left")
    ndi.add_argument("--motion", **motion)
    ndi.add_argument("--link-dir", default=None, help="folder for the stable name ttyNDI0 (default: a new temporary "
                                                      "folder)")
    ndi.set_defaults(func=cmd_emulate)
