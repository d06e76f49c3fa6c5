"""rigctl.devices: wire protocols and the host-side clients of the rig's two boards (pyserial + pymodbus).

Public API (re-exported here, imported on first use): the drum controller's Modbus client (``DrumClient``, its
decoded ``DrumStatus``), the taxel streamer's client (``TaxelStream``, ``StreamStats``, ``Capture``), framing
(``FrameParser``, ``encode_frames``, ``RingBuffer``), ports (``find_ports``, ``PortInfo``), the hardware backend
(``SerialBackend``) and the errors. The numbers of the spec are :mod:`rigctl.devices.wire`.
"""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "SerialBackend": "rigctl.devices.backend",
    "DrumClient": "rigctl.devices.drum",
    "DrumStatus": "rigctl.devices.drum",
    "DrumError": "rigctl.devices.errors",
    "DrumFault": "rigctl.devices.errors",
    "DrumTimeout": "rigctl.devices.errors",
    "ModbusExceptionError": "rigctl.devices.errors",
    "SetpointRangeError": "rigctl.devices.errors",
    "TaxelLinkLost": "rigctl.devices.errors",
    "TaxelStreamError": "rigctl.devices.errors",
    "FrameParser": "rigctl.devices.frames",
    "encode_frames": "rigctl.devices.frames",
    "PortInfo": "rigctl.devices.ports",
    "find_ports": "rigctl.devices.ports",
    "RingBuffer": "rigctl.devices.ring",
    "Capture": "rigctl.devices.taxel_stream",
    "StreamStats": "rigctl.devices.taxel_stream",
    "TaxelStream": "rigctl.devices.taxel_stream",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.devices.backend import SerialBackend as SerialBackend
    from rigctl.devices.drum import DrumClient as DrumClient, DrumStatus as DrumStatus
    from rigctl.devices.errors import (
        DrumError as DrumError,
        DrumFault as DrumFault,
        DrumTimeout as DrumTimeout,
        ModbusExceptionError as ModbusExceptionError,
        SetpointRangeError as SetpointRangeError,
        TaxelLinkLost as TaxelLinkLost,
        TaxelStreamError as TaxelStreamError,
    )
    from rigctl.devices.frames import FrameParser as FrameParser, encode_frames as encode_frames
    from rigctl.devices.ports import PortInfo as PortInfo, find_ports as find_ports
    from rigctl.devices.ring import RingBuffer as RingBuffer
    from rigctl.devices.taxel_stream import Capture as Capture, StreamStats as StreamStats, TaxelStream as TaxelStream
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
