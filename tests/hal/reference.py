"""Plain-Python reference implementations of the contract's CRC, written from the CRC catalogue's
definition and sharing nothing with hal/, for tests to check the compiled ones against."""

from __future__ import annotations


def reference_crc8(data: bytes) -> int:
    """CRC-8/SAE-J1850 bit by bit, as the CRC catalogue defines it (width 8, polynomial 0x1D,
    initial value 0xFF, not reflected, final XOR 0xFF; check value 0x4B over "123456789")."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def reference_frame_crc(data_id: int, data: bytes, crc_byte: int) -> int:
    """The contract's CRC: over the Data ID's low byte, its high byte, then the data bytes without
    the CRC byte."""
    data = bytes(data)
    return reference_crc8(bytes([data_id & 0xFF, data_id >> 8]) + data[:crc_byte] + data[crc_byte + 1:])


def low_byte_crc(frame_id: int, data: bytes, crc_byte: int) -> int:
    """The CRC of the contract before the Data IDs: over the identifier's low byte, then the data
    bytes without the CRC byte."""
    data = bytes(data)
    return reference_crc8(bytes([frame_id & 0xFF]) + data[:crc_byte] + data[crc_byte + 1:])
