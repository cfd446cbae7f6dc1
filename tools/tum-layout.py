#!/usr/bin/env python3
"""Writes 7-Scenes frames as a TUM RGB-D sequence, to try octstore's TUM reader and to
benchmark it on the same frames as the 7-Scenes folder.

    python3 tools/tum-layout.py ../shared/data/7scenes-redkitchen OUT [--stride 10] [--limit 100]

OUT gets depth/<timestamp>.png (16-bit, 5000 units per metre; 0 stays invalid), depth.txt,
groundtruth.txt (timestamp tx ty tz qx qy qz qw, camera-to-world, 5 ms after each frame) and
intrinsics.txt (the 7-Scenes camera-intrinsics.txt) to pass with --intrinsics. Frames are 1/30 s apart. Needs only
the Python standard library (the PNGs are read and written with zlib).
"""
import argparse
import math
import struct
import zlib
from pathlib import Path


def read_png16(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path}: not a PNG"
    pos, idat, width = 8, b"", None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            width, height, depth, color = struct.unpack(">IIBB", body[:10])
            assert depth == 16 and color == 0, f"{path}: expected 16-bit grey"
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    raw = zlib.decompress(idat)
    stride = width * 2
    rows, prev = [], bytearray(stride)
    for y in range(height):
        f = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - 2] if i >= 2 else 0
            b = prev[i]
            c = prev[i - 2] if i >= 2 else 0
            if f == 1:
                line[i] = (line[i] + a) & 255
            elif f == 2:
                line[i] = (line[i] + b) & 255
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    return width, height, [struct.unpack(f">{width}H", r) for r in rows]


def write_png16(path, width, height, rows):
    raw = b"".join(b"\x00" + struct.pack(f">{width}H", *r) for r in rows)
    chunk = lambda kind, body: struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def quaternion(m):
    """(x, y, z, w) of the rotation part of a row-major 3x3 list, orthonormalised by the trace method."""
    t = m[0][0] + m[1][1] + m[2][2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    i = max(range(3), key=lambda k: m[k][k])
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + m[i][i] - m[j][j] - m[k][k]) * 2
    q = [0.0, 0.0, 0.0, (m[k][j] - m[j][k]) / s]
    q[i], q[j], q[k] = 0.25 * s, (m[j][i] + m[i][j]) / s, (m[k][i] + m[i][k]) / s
    n = math.sqrt(sum(v * v for v in q))
    return tuple(v / n for v in q)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--limit", type=int)
    args = parser.parse_args()
    frames = sorted(args.source.glob("frame-*.depth.png"))[::args.stride][:args.limit]
    (args.out / "depth").mkdir(parents=True, exist_ok=True)
    depth_list, truth = ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for depth in frames:
        n = int(depth.name.split("-")[1].split(".")[0])
        time = 1305031102.0 + n / 30.0
        width, height, rows = read_png16(depth)
        scaled = [[v if v in (0, 65535) else min(v * 5, 65534) for v in r] for r in rows]
        name = f"depth/{time:.6f}.png"
        write_png16(args.out / name, width, height, scaled)
        depth_list.append(f"{time:.6f} {name}")
        values = [float(v) for v in depth.with_name(depth.name.replace(".depth.png", ".pose.txt")).read_text().split()]
        m = [values[0:4], values[4:8], values[8:12]]
        x, y, z, w = quaternion([r[:3] for r in m])
        truth.append(f"{time + 0.005:.6f} {m[0][3]} {m[1][3]} {m[2][3]} {x} {y} {z} {w}")
    (args.out / "depth.txt").write_text("\n".join(depth_list) + "\n")
    (args.out / "groundtruth.txt").write_text("\n".join(truth) + "\n")
    (args.out / "intrinsics.txt").write_text((args.source / "camera-intrinsics.txt").read_text())
    print(f"wrote {len(frames)} frames to {args.out}")


if __name__ == "__main__":
    main()
