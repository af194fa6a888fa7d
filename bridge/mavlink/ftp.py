"""MAVLink FTP: enough to say "no files here", so ground stations fall back at once.

QGroundControl (ArduPilot firmware) and MAVProxy (``param_ftp``, on by default)
first try to download the parameters as a file over MAVLink FTP
(``@PARAM/param.pck``) and only fall back to PARAM_REQUEST_LIST when that
fails: at once on a NAK "file not found", after about 12 s when nobody
answers. The bridge keeps no files, so every request gets that NAK (session
resets and terminations an ACK). PURE: a request in, the reply out.

FILE_TRANSFER_PROTOCOL.payload (MAVLink FTP header, little endian)::

    seq u16 | session u8 | opcode u8 | size u8 | req_opcode u8 | burst_complete u8 |
    padding u8 | offset u32 | data[239]
"""

from __future__ import annotations

import struct
from typing import Any

from bridge.mavlink.dialect import Message, message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short

_HEADER = struct.Struct("<HBBBBBBI")
TERMINATE_SESSION = 1
RESET_SESSIONS = 2
ACK = 128
NAK = 129
ERR_FILE_NOT_FOUND = 10  #: MAV_FTP_ERR_FILENOTFOUND


def reply(request: Any, network: int = 0) -> Message | None:
    """The answer to one FILE_TRANSFER_PROTOCOL request (None for a reply someone sent us)."""
    raw = bytes(request.payload)
    if len(raw) < _HEADER.size:
        raw += bytes(_HEADER.size - len(raw))
    seq, session, opcode, _size, _req, _burst, _pad, offset = _HEADER.unpack_from(raw)
    if opcode in (ACK, NAK):
        return None
    if opcode in (TERMINATE_SESSION, RESET_SESSIONS):
        answer, data = ACK, b""
    else:
        answer, data = NAK, bytes((ERR_FILE_NOT_FOUND,))
    header = _HEADER.pack((seq + 1) & 0xFFFF, session, answer, len(data), opcode, 0, 0, offset)
    payload = header + data
    return message(
        M.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL,
        target_network=network,
        target_system=request.get_srcSystem(),
        target_component=request.get_srcComponent(),
        payload=list(payload + bytes(251 - len(payload))),
    )
