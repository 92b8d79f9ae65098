#!/usr/bin/env python3
"""Writes tests/data/two_scans.e57 with libE57Format (through pye57), the
library most scanner software writes E57 with, so that the reader is tested
on a file another implementation wrote. Run once; the file is committed.

Two scans of a small scene 500000, 4400000, 200 from the origin (as UTM
coordinates are), each stored in its scanner's own frame with its pose:
scan 0 sees the ground (x, y in 0..9 m, 1 m steps, z = 0) and the wall x = 5
(y in 0..9, z in 1..4); scan 1 sees the wall y = 8 (x in 0..9, z in 1..4) and
holds one more record flagged invalid (cartesianInvalidState = 2). Every
point carries an intensity and a colour. tests/map/io.rs rebuilds the same
points and checks what the reader returns.

usage: python3 -m venv venv && venv/bin/pip install pye57 numpy &&
       venv/bin/python scripts/make_e57_fixture.py tests/data/two_scans.e57
"""
import math
import sys

import numpy as np
import pye57

OFFSET = np.array([500000.0, 4400000.0, 200.0])


def quaternion(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = math.radians(degrees) / 2
    return np.array([math.cos(h), *(math.sin(h) * axis)])


def rotation(q):
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def scene():
    ground = [(x, y, 0.0) for x in range(10) for y in range(10)]
    wall_x = [(5.0, y, z) for y in range(10) for z in range(1, 5)]
    wall_y = [(x, 8.0, z) for x in range(10) for z in range(1, 5)]
    return np.array(ground + wall_x, float), np.array(wall_y, float)


def write_scan(e57, world, q, t, invalid_extra):
    local = (world + OFFSET - t) @ rotation(q)  # R^T (p - t), row vectors
    state = np.zeros(len(local), np.int8)
    if invalid_extra:
        local = np.vstack([local, [[0.0, 0.0, 0.0]]])
        state = np.append(state, np.int8(2))
    n = len(local)
    data = {
        "cartesianX": local[:, 0].copy(),
        "cartesianY": local[:, 1].copy(),
        "cartesianZ": local[:, 2].copy(),
        "cartesianInvalidState": state,
        "intensity": np.linspace(0.1, 0.9, n).astype(np.float32),
        "colorRed": np.full(n, 200, np.uint8),
        "colorGreen": np.full(n, 100, np.uint8),
        "colorBlue": np.full(n, 50, np.uint8),
    }
    e57.write_scan_raw(data, rotation=q, translation=t)


def main():
    out = sys.argv[1]
    scan0, scan1 = scene()
    e57 = pye57.E57(out, mode="w")
    write_scan(e57, scan0, quaternion([0, 0, 1], 30.0), OFFSET + [2.0, 3.0, 1.5], False)
    write_scan(e57, scan1, quaternion([1, 1, 1], 20.0), OFFSET + [6.0, 1.0, 1.6], True)
    e57.close()


if __name__ == "__main__":
    main()
