"""rigctl.devices: wire protocols and the host-side clients of the rig's two boards (pyserial + pymodbus).

Public API (re-exported here, imported on first use): the drum controller's Modbus client (``DrumClient``, its
decoded ``DrumStatus``), the taxel streamer's client (``TaxelStream``, ``StreamStats``, ``Capture``), framing
(``FrameParser``, ``encode_frames``, ``RingBuffer``), ports (``find_ports``, ``PortInfo``), the hardware backend
(``SerialBackend``) and the errors. The numbers of the spec are :mod:`rigctl.devices.wire`.
"""

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
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
