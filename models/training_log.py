"""Training logs: a CSV file and TensorBoard-compatible event files, with no extra dependency.

An event file is a sequence of TFRecords (``uint64`` length, masked CRC-32C of the length, the
payload, masked CRC-32C of the payload), each payload an ``Event`` protocol buffer: the first holds
``file_version = "brain.Event:2"``, the others ``wall_time``, ``step`` and a ``Summary`` of scalar
values. Only the handful of protobuf fields needed are encoded here; TensorBoard reads the files
(``tensorboard --logdir OUTPUT_DIR``).
"""

from __future__ import annotations

import csv
import os
import socket
import struct
import time
from pathlib import Path

_CRC32C_POLY = 0x82F63B78  # Castagnoli, reflected


def _crc32c_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ _CRC32C_POLY if crc & 1 else crc >> 1
        table.append(crc)
    return table


_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) of ``data``."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc = _TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    """The TFRecord masking of CRC-32C: rotate right by 15 and add a constant."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        bits = value & 0x7F
        value >>= 7
        if value:
            out.append(bits | 0x80)
        else:
            out.append(bits)
            return bytes(out)


def _field(number: int, wire_type: int, payload: bytes) -> bytes:
    return _varint((number << 3) | wire_type) + payload


def _length_delimited(number: int, payload: bytes) -> bytes:
    return _field(number, 2, _varint(len(payload)) + payload)


def encode_event(
    wall_time: float,
    step: int = 0,
    scalars: dict[str, float] | None = None,
    file_version: str | None = None,
) -> bytes:
    """An ``Event`` message: wall_time (1), step (2), file_version (3) and summary (5) fields."""
    out = _field(1, 1, struct.pack("<d", wall_time)) + _field(2, 0, _varint(step))
    if file_version is not None:
        out += _length_delimited(3, file_version.encode())
    if scalars:
        values = b"".join(
            _length_delimited(
                1,
                _length_delimited(1, tag.encode()) + _field(2, 5, struct.pack("<f", float(value))),
            )
            for tag, value in scalars.items()
        )
        out += _length_delimited(5, values)
    return out


def tfrecord(payload: bytes) -> bytes:
    """One TFRecord framing ``payload``."""
    length = struct.pack("<Q", len(payload))
    return (
        length
        + struct.pack("<I", masked_crc32c(length))
        + payload
        + struct.pack("<I", masked_crc32c(payload))
    )


class TrainingLog:
    """Scalars per step, appended to ``log.csv`` and to a new TensorBoard event file per run.

    Args:
        folder: Where the files go (created if missing).
        columns: The scalar names, in CSV column order after ``step`` and ``wall_time``.
    """

    def __init__(self, folder: str | os.PathLike[str], columns: list[str]) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.columns = columns
        self.csv_path = self.folder / "log.csv"
        new = not self.csv_path.exists()
        self._csv = self.csv_path.open("a", newline="", encoding="utf-8")
        self._writer = csv.writer(self._csv)
        if new:
            self._writer.writerow(["step", "wall_time", *columns])
        name = f"events.out.tfevents.{time.time_ns()}.{socket.gethostname()}.{os.getpid()}"
        self.events_path = self.folder / name
        self._events = self.events_path.open("ab")
        self._events.write(tfrecord(encode_event(time.time(), file_version="brain.Event:2")))

    def write(self, step: int, **scalars: float) -> None:
        """Record the scalars of one step (unknown names raise ``KeyError``)."""
        unknown = set(scalars) - set(self.columns)
        if unknown:
            raise KeyError(f"TrainingLog.write(): unknown columns {sorted(unknown)}")
        now = time.time()
        self._writer.writerow([step, f"{now:.3f}", *(scalars.get(c, "") for c in self.columns)])
        self._events.write(tfrecord(encode_event(now, step, scalars)))
        self._csv.flush()
        self._events.flush()

    def close(self) -> None:
        """Close the files."""
        self._csv.close()
        self._events.close()
