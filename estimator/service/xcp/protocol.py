"""The XCP wire (ASAM MCD-1 XCP 1.x, Ethernet transport): command and error codes, the packet
identifiers, and the 4-byte Ethernet header (LEN, CTR, little-endian) in front of every packet."""

from __future__ import annotations

import struct

# packet identifiers, slave -> master
RES, ERR, EV, SERV = 0xFF, 0xFE, 0xFD, 0xFC

# commands (master -> slave), the first byte of a CTO
CONNECT, DISCONNECT, GET_STATUS, SYNCH = 0xFF, 0xFE, 0xFD, 0xFC
GET_COMM_MODE_INFO, GET_ID, SET_REQUEST, GET_SEED, UNLOCK = 0xFB, 0xFA, 0xF9, 0xF8, 0xF7
SET_MTA, UPLOAD, SHORT_UPLOAD, BUILD_CHECKSUM = 0xF6, 0xF5, 0xF4, 0xF3
TRANSPORT_LAYER_CMD, USER_CMD = 0xF2, 0xF1
DOWNLOAD, DOWNLOAD_NEXT, DOWNLOAD_MAX, SHORT_DOWNLOAD, MODIFY_BITS = 0xF0, 0xEF, 0xEE, 0xED, 0xEC
SET_CAL_PAGE, GET_CAL_PAGE, GET_PAG_PROCESSOR_INFO, GET_SEGMENT_INFO, GET_PAGE_INFO = 0xEB, 0xEA, 0xE9, 0xE8, 0xE7
SET_SEGMENT_MODE, GET_SEGMENT_MODE, COPY_CAL_PAGE = 0xE6, 0xE5, 0xE4
CLEAR_DAQ_LIST, SET_DAQ_PTR, WRITE_DAQ, SET_DAQ_LIST_MODE, GET_DAQ_LIST_MODE = 0xE3, 0xE2, 0xE1, 0xE0, 0xDF
START_STOP_DAQ_LIST, START_STOP_SYNCH, GET_DAQ_CLOCK, READ_DAQ = 0xDE, 0xDD, 0xDC, 0xDB
GET_DAQ_PROCESSOR_INFO, GET_DAQ_RESOLUTION_INFO, GET_DAQ_LIST_INFO, GET_DAQ_EVENT_INFO = 0xDA, 0xD9, 0xD8, 0xD7
FREE_DAQ, ALLOC_DAQ, ALLOC_ODT, ALLOC_ODT_ENTRY = 0xD6, 0xD5, 0xD4, 0xD3
LEVEL_1_COMMAND, GET_VERSION = 0xC0, 0x00

# the optional commands the slave answers (the A2L's OPTIONAL_CMD; CONNECT, DISCONNECT, GET_STATUS and
# SYNCH are every slave's)
OPTIONAL_COMMANDS = ("GET_COMM_MODE_INFO", "GET_ID", "SET_MTA", "UPLOAD", "SHORT_UPLOAD", "DOWNLOAD",
                     "SET_CAL_PAGE", "GET_CAL_PAGE", "GET_PAG_PROCESSOR_INFO", "GET_SEGMENT_INFO", "GET_PAGE_INFO",
                     "COPY_CAL_PAGE", "CLEAR_DAQ_LIST", "SET_DAQ_PTR", "WRITE_DAQ", "SET_DAQ_LIST_MODE",
                     "GET_DAQ_LIST_MODE", "START_STOP_DAQ_LIST", "START_STOP_SYNCH", "GET_DAQ_CLOCK", "READ_DAQ",
                     "GET_DAQ_PROCESSOR_INFO", "GET_DAQ_RESOLUTION_INFO", "GET_DAQ_LIST_INFO", "GET_DAQ_EVENT_INFO",
                     "FREE_DAQ", "ALLOC_DAQ", "ALLOC_ODT", "ALLOC_ODT_ENTRY")

# error codes
ERR_CMD_SYNCH, ERR_CMD_BUSY, ERR_DAQ_ACTIVE, ERR_PGM_ACTIVE = 0x00, 0x10, 0x11, 0x12
ERR_CMD_UNKNOWN, ERR_CMD_SYNTAX, ERR_OUT_OF_RANGE, ERR_WRITE_PROTECTED = 0x20, 0x21, 0x22, 0x23
ERR_ACCESS_DENIED, ERR_ACCESS_LOCKED, ERR_PAGE_NOT_VALID, ERR_MODE_NOT_VALID = 0x24, 0x25, 0x26, 0x27
ERR_SEGMENT_NOT_VALID, ERR_SEQUENCE, ERR_DAQ_CONFIG, ERR_MEMORY_OVERFLOW, ERR_GENERIC = 0x28, 0x29, 0x2A, 0x30, 0x31

PROTOCOL_LAYER_VERSION = 1      # XCP 1.x
TRANSPORT_LAYER_VERSION = 1     # XCP on Ethernet 1.x
MAX_CTO = 255                   # bytes of a command or response packet
MAX_DTO = 1400                  # bytes of a DAQ packet (one UDP datagram below a 1500-byte MTU)
HEADER = struct.Struct("<HH")   # LEN (packet bytes after the header), CTR
TIMEOUTS_MS = (1000, 2000, 0, 0, 0, 0, 0)   # T1 (a command's answer) .. T7, as the A2L states them


class XcpError(Exception):
    """A command the slave answers with ERR and ``code`` (one of the ERR_* codes)."""

    def __init__(self, code: int, why: str = "") -> None:
        super().__init__(why or f"XCP error 0x{code:02X}")
        self.code = code


def packets(datagram: bytes) -> list[tuple[int, bytes]] | None:
    """The (CTR, packet) pairs of one UDP datagram (XCP on Ethernet may pack several), None when its
    headers do not add up (a malformed datagram: dropped and counted, never answered)."""
    out = []
    pos = 0
    while pos < len(datagram):
        if len(datagram) - pos < HEADER.size:
            return None
        length, ctr = HEADER.unpack_from(datagram, pos)
        pos += HEADER.size
        if length == 0 or length > MAX_CTO or pos + length > len(datagram):
            return None
        out.append((ctr, datagram[pos:pos + length]))
        pos += length
    return out or None


def frame(ctr: int, packet: bytes) -> bytes:
    """One packet with its Ethernet header."""
    return HEADER.pack(len(packet), ctr & 0xFFFF) + packet


def error(code: int) -> bytes:
    """The ERR packet of ``code``."""
    return bytes((ERR, code))
