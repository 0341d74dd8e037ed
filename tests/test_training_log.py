"""Training logs: CRC-32C, TFRecord framing and the Event protobuf, read back independently."""

from __future__ import annotations

import csv
import struct

import pytest

from svr.models.training_log import TrainingLog, crc32c, masked_crc32c


def test_crc32c_standard_check_value():
    assert crc32c(b"123456789") == 0xE3069283  # the CRC-32C catalogue's check value
    assert crc32c(b"") == 0


def read_records(path):
    data = path.read_bytes()
    records, i = [], 0
    while i < len(data):
        (length,) = struct.unpack("<Q", data[i : i + 8])
        (length_crc,) = struct.unpack("<I", data[i + 8 : i + 12])
        assert length_crc == masked_crc32c(data[i : i + 8])
        payload = data[i + 12 : i + 12 + length]
        (payload_crc,) = struct.unpack("<I", data[i + 12 + length : i + 16 + length])
        assert payload_crc == masked_crc32c(payload)
        records.append(payload)
        i += 16 + length
    return records


def read_varint(buf, i):
    """A protobuf varint at ``buf[i]``: (value, index after it)."""
    value, shift = 0, 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def parse(buf):
    """A minimal protobuf reader: {field number: [values]} (varint, fixed64, bytes, fixed32)."""
    out, i = {}, 0
    while i < len(buf):
        key, i = read_varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = read_varint(buf, i)
        elif wire == 1:
            value, i = buf[i : i + 8], i + 8
        elif wire == 5:
            value, i = buf[i : i + 4], i + 4
        else:
            length, i = read_varint(buf, i)
            value, i = buf[i : i + length], i + length
        out.setdefault(number, []).append(value)
    return out


def test_csv_and_event_file(tmp_path):
    log = TrainingLog(tmp_path, ["loss", "lr"])
    log.write(10, loss=0.5, lr=1e-3)
    log.write(20, loss=0.25)
    with pytest.raises(KeyError, match="unknown columns"):
        log.write(30, accuracy=1.0)
    log.close()
    rows = list(csv.reader((tmp_path / "log.csv").open()))
    assert rows[0] == ["step", "wall_time", "loss", "lr"]
    assert rows[1][0] == "10" and float(rows[1][2]) == 0.5 and rows[2][3] == ""
    records = [parse(r) for r in read_records(log.events_path)]
    assert records[0][3] == [b"brain.Event:2"]
    step, summary = records[1][2][0], parse(records[1][5][0])
    values = {parse(v)[1][0].decode(): struct.unpack("<f", parse(v)[2][0])[0] for v in summary[1]}
    assert step == 10 and values == pytest.approx({"loss": 0.5, "lr": 1e-3})
    assert struct.unpack("<d", records[2][1][0])[0] > 1.6e9  # wall time in seconds
    # a second run appends to the CSV and starts a new event file
    again = TrainingLog(tmp_path, ["loss", "lr"])
    again.write(40, loss=0.1)
    again.close()
    assert len(list(csv.reader((tmp_path / "log.csv").open()))) == 4
    assert again.events_path != log.events_path
