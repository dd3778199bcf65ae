"""The CiA 301/402 objects the app uses, as one canopen ObjectDictionary shared by the driver's RemoteNodes
and the emulator's LocalNodes (what an EDS file would describe for a position drive such as a maxon EPOS4)."""

from __future__ import annotations

import canopen
from canopen.objectdictionary import ODRecord, ODVariable, datatypes

DEVICE_TYPE_CIA402 = 0x00020192  # profile 402, servo drive
STATUSWORD = 0x6041
POSITION_ACTUAL = 0x6064
ERROR_REGISTER = 0x1001
PRODUCER_HEARTBEAT = 0x1017
ERROR_CODE = 0x603F
STATUS_FAULT_BIT = 1 << 3
STATUS_OPERATION_ENABLED = 0x0237
TPDO1_COMMUNICATION = 0x1800
TPDO1_MAPPING = 0x1A00
TPDO_NOT_VALID = 1 << 31  # COB-ID bit 31: the PDO does not exist / is not valid
RTR_NOT_ALLOWED = 1 << 30  # COB-ID bit 30: no RTR allowed on this PDO (some devices refuse to clear it)
TPDO_EXTENDED_ID = 1 << 29  # COB-ID bit 29: 29-bit identifier

# CiA 301 emergency error codes, by class (the high byte; the codes below a class name its sub-classes)
EMCY_CLASSES = {
    0x00: "error reset or no error",
    0x10: "generic error",
    0x20: "current", 0x21: "current, device input side", 0x22: "current inside the device",
    0x23: "current, device output side",
    0x30: "voltage", 0x31: "mains voltage", 0x32: "voltage inside the device", 0x33: "output voltage",
    0x40: "temperature", 0x41: "ambient temperature", 0x42: "device temperature",
    0x50: "device hardware",
    0x60: "device software", 0x61: "internal software", 0x62: "user software", 0x63: "data set",
    0x70: "additional modules",
    0x80: "monitoring", 0x81: "monitoring: communication", 0x82: "monitoring: protocol error",
    0x90: "external error",
    0xF0: "additional functions",
    0xFF: "device specific",
}


def emcy_description(code: int) -> str:
    """What a CiA 301 emergency error code means, from its class (high byte; its sub-class where CiA 301 names
    one), e.g. 0x4210 'device temperature', 0x7305 'additional modules', 0x8130 'monitoring: communication'.
    A device profile's code within a class gets the class (0x5530: 'device hardware'); a code of no class is
    'reserved error class 0xNN'."""
    high = (code >> 8) & 0xFF
    if high in EMCY_CLASSES:
        return EMCY_CLASSES[high]
    if 0x10 <= high < 0xA0 or 0xF0 <= high < 0xFF:
        return EMCY_CLASSES[high & 0xF0]
    return f"reserved error class 0x{high:02X}"


def _var(name, index, subindex, dtype, access="rw", default=0) -> ODVariable:
    v = ODVariable(name, index, subindex)
    v.data_type = dtype
    v.access_type = access
    v.default = default
    return v


def cia402_object_dictionary() -> canopen.ObjectDictionary:
    od = canopen.ObjectDictionary()
    for var in (
        _var("Device type", 0x1000, 0, datatypes.UNSIGNED32, "ro", DEVICE_TYPE_CIA402),
        _var("Error register", ERROR_REGISTER, 0, datatypes.UNSIGNED8, "ro"),
        _var("Producer heartbeat time", PRODUCER_HEARTBEAT, 0, datatypes.UNSIGNED16),
        _var("Error code", ERROR_CODE, 0, datatypes.UNSIGNED16, "ro"),
        _var("Statusword", STATUSWORD, 0, datatypes.UNSIGNED16, "ro", STATUS_OPERATION_ENABLED),
        _var("Modes of operation display", 0x6061, 0, datatypes.INTEGER8, "ro", 1),
        _var("Position actual value", POSITION_ACTUAL, 0, datatypes.INTEGER32, "ro"),
        _var("Velocity actual value", 0x606C, 0, datatypes.INTEGER32, "ro"),
    ):
        od.add_object(var)
    for n in range(4):
        com = ODRecord(f"TPDO{n + 1} communication parameter", 0x1800 + n)
        com.add_member(_var("Highest sub-index supported", 0x1800 + n, 0, datatypes.UNSIGNED8, "ro", 5))
        com.add_member(_var("COB-ID", 0x1800 + n, 1, datatypes.UNSIGNED32, "rw", 0x80000000 | (0x180 + 0x100 * n)))
        com.add_member(_var("Transmission type", 0x1800 + n, 2, datatypes.UNSIGNED8, "rw", 1))
        com.add_member(_var("Inhibit time", 0x1800 + n, 3, datatypes.UNSIGNED16))
        com.add_member(_var("Event timer", 0x1800 + n, 5, datatypes.UNSIGNED16))
        od.add_object(com)
        mapping = ODRecord(f"TPDO{n + 1} mapping parameter", 0x1A00 + n)  # RECORD in CiA 301
        mapping.add_member(_var("Number of mapped objects", 0x1A00 + n, 0, datatypes.UNSIGNED8, "rw", 0))
        for sub in range(1, 9):
            mapping.add_member(_var(f"Mapped object {sub}", 0x1A00 + n, sub, datatypes.UNSIGNED32, "rw", 0))
        od.add_object(mapping)
    return od
