"""``cellcal calibrate`` (a real subprocess) on hostile station sets (issue 11).

Each bad image becomes a rejected station with its reason while the good ones still calibrate;
nothing is read outside the station directory, nothing but regular files is opened, oversized
images are refused from their header. Peak memory is the child's own ``ru_maxrss`` (wait4).
"""

from __future__ import annotations

import json
import os
import re
import struct
import zlib
from pathlib import Path

import cv2
import pytest

from tests.support.cli import MEMORY_LIMIT, run_cli
from tests.support.stations import write_image_set


def zero_png(path: Path, width: int, height: int, *, colour: bool = True) -> Path:
    """A valid PNG of black pixels, written without ever holding the pixels.

    Rows of zeros (filter byte 0 included) are all zeros, so the zlib stream is one
    compressed block repeated: after a full flush the raw-deflate compressor starts afresh and
    emits the same bytes for the same input. Adler-32 of n zero bytes is ``(n mod 65521) << 16
    | 1`` (RFC 1950).
    """
    channels = 3 if colour else 1
    total = height * (1 + channels * width)
    chunk = 1 << 20
    deflate = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = deflate.compress(bytes(chunk)) + deflate.flush(zlib.Z_FULL_FLUSH)
    repeated, rest = divmod(total, chunk)
    tail = deflate.compress(bytes(rest)) + deflate.flush(zlib.Z_FINISH)
    stream = (b"\x78\xda" + block * repeated + tail
              + struct.pack(">I", ((total % 65521) << 16) | 1))

    def chunk_bytes(kind: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body)))

    header = struct.pack(">IIBBBBB", width, height, 8, 2 if colour else 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk_bytes(b"IHDR", header)
                     + chunk_bytes(b"IDAT", stream) + chunk_bytes(b"IEND", b""))
    return path


def test_zero_png_is_a_valid_image(tmp_path):
    image = cv2.imread(str(zero_png(tmp_path / "z.png", 700, 300)), cv2.IMREAD_UNCHANGED)
    assert image.shape == (300, 700, 3) and not image.any()


def corrupt_png(source: Path, target: Path) -> Path:
    """``source`` with one byte of its image data flipped (the chunk CRC no longer matches)."""
    data = bytearray(source.read_bytes())
    data[len(data) // 2] ^= 0xFF
    target.write_bytes(bytes(data))
    return target


@pytest.fixture
def hostile_set(tmp_path):
    """15 rendered stations; 9 of them name hostile files. Returns (dir, expected reasons)."""
    d = write_image_set(tmp_path / "set", n=15)
    outside = tmp_path / "outside.png"
    cv2.imwrite(str(outside), cv2.imread(str(d / "005.png")))  # a good image, but outside
    (d / "sub").mkdir()
    (d / "sub" / "empty.png").write_bytes(b"")
    os.symlink(outside, d / "link.png")
    os.symlink("/dev/zero", d / "zero.png")
    os.mkfifo(d / "fifo.png")
    zero_png(d / "huge.png", 20000, 20000)
    corrupt_png(d / "006.png", d / "sub" / "crc.png")
    (d / "sub" / "moved.png").write_bytes((d / "007.png").read_bytes())  # subfolders are fine
    names = {"000": "sub/empty.png", "001": "../outside.png", "002": "/etc/passwd",
             "003": "link.png", "004": "fifo.png", "005": "zero.png", "006": "huge.png",
             "008": "sub/crc.png", "007": "sub/moved.png", "009": "a\0b.png"}
    doc = json.loads((d / "stations.json").read_text())
    for station in doc["stations"]:
        station["image"] = names.get(station["id"], station["image"])
    (d / "stations.json").write_text(json.dumps(doc))
    expected = {
        "000": r"^image file 'sub/empty.png' is empty \(0 bytes\)$",
        "001": r"^image path '../outside.png' leads outside the station directory$",
        "002": r"^image path '/etc/passwd' is absolute: name files relative to the station",
        "003": r"^image path 'link.png' leads outside the station directory$",
        "004": r"^image path 'fifo.png' is a FIFO \(named pipe\), not a regular file$",
        "005": r"^image path 'zero.png' leads outside the station directory$",
        "006": r"^image file 'huge.png' is 20000x20000 = 400 MP, more than the 25 MP allowed$",
        "008": r"^image file 'sub/crc.png' is corrupt \(.*CRC error.*\)$",
        "009": r"^image path 'a\\x00b.png' contains a NUL character$",
    }
    return d, expected


def test_hostile_files_are_rejected_per_station(tmp_path, hostile_set):
    d, expected = hostile_set
    out = tmp_path / "result.json"
    code, _, stderr, peak = run_cli("calibrate", str(d), "--out", str(out))
    assert code == 0, stderr
    assert stderr.strip().splitlines()[-1] == f"wrote {out}"
    assert "Traceback" not in stderr
    # libpng speaks only through the rejection reasons, never on its own lines
    assert not [line for line in stderr.splitlines() if line.lstrip("\r").startswith("libpng")]
    doc = json.loads(out.read_text())
    rejected = {r["id"]: r["reason"] for r in doc["rejected"]}
    for sid, reason in rejected.items():  # every rejection is said on the terminal (issue 19)
        assert f"cellcal: station {sid} rejected: {reason}" in stderr, (sid, stderr)
    assert set(rejected) == set(expected), rejected
    for sid, pattern in expected.items():
        assert re.search(pattern, rejected[sid]), (sid, rejected[sid])
    used = {s["id"] for s in doc["stations"]}
    assert "007" in used and used.isdisjoint(expected)
    assert doc["hand_eye"] is not None
    assert peak < MEMORY_LIMIT, f"peak RSS {peak / 1e6:.0f} MB"


def test_only_bad_files_is_one_line_and_exit_2(tmp_path):
    d = write_image_set(tmp_path / "set", n=3)
    (d / "000.jpg").write_bytes(b"")
    zero_png(d / "001.jpg", 16000, 16000, colour=True)
    os.mkfifo(d / "fifo.png")
    doc = json.loads((d / "stations.json").read_text())
    doc["stations"][2]["image"] = "fifo.png"
    (d / "stations.json").write_text(json.dumps(doc))
    code, _, stderr, peak = run_cli("calibrate", str(d), "--max-image-pixels", "1000000")
    assert code == 2
    assert stderr.count("\n") == 1 and stderr.startswith(
        "cellcal: error: only 0 of 3 stations usable, need at least 3 (000: image file "
        "'000.jpg' is empty (0 bytes); 001: image file '001.jpg' is 16000x16000 = 256 MP, "
        "more than the 1 MP allowed; 002: image path 'fifo.png' is a FIFO"), stderr
    assert peak < MEMORY_LIMIT


def test_station_count_is_bounded(tmp_path):
    d = write_image_set(tmp_path / "set", n=5)
    code, _, stderr, _ = run_cli("calibrate", str(d), "--max-stations", "4")
    assert code == 2
    assert stderr == (f"cellcal: error: {d / 'stations.json'}: 5 stations, more than the 4 "
                      "allowed (--max-stations)\n")


def test_oversized_stations_file_is_refused_before_reading(tmp_path):
    d = tmp_path / "set"
    d.mkdir()
    (d / "stations.json").write_bytes(b" " * 30_000)  # not even parsed
    code, _, stderr, _ = run_cli("calibrate", str(d), "--max-stations", "10")
    assert code == 2
    assert stderr == (f"cellcal: error: {d / 'stations.json'}: 0 MB, more than the 0 MB "
                      "allowed for 10 stations\n")


def test_stations_file_that_is_a_fifo_is_refused(tmp_path):
    os.mkfifo(tmp_path / "stations.json")
    code, _, stderr, _ = run_cli("calibrate", str(tmp_path))
    assert code == 2
    assert stderr == f"cellcal: error: {tmp_path / 'stations.json'}: not a regular file\n"
