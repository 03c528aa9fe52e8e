"""CSV tables a spreadsheet opens: poses and contacts (mm, unit quaternions x, y, z, w)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from chipstack.core.stack import BatchResult, Stack


def fmt(value: float, digits: int = 6) -> str:
    """A number for a CSV cell: ``digits`` significant digits; empty when not finite."""
    return f"{value:.{digits}g}" if np.isfinite(value) else ""


POSE_COLUMNS = (
    "chip",
    "batch",
    "shape",
    "x_mm",
    "y_mm",
    "z_mm",
    "qx",
    "qy",
    "qz",
    "qw",
    "inside_target",
)
CONTACT_COLUMNS = (
    "chip_a",
    "chip_b",
    "xa_mm",
    "ya_mm",
    "za_mm",
    "xb_mm",
    "yb_mm",
    "zb_mm",
    "nx",
    "ny",
    "nz",
    "distance_mm",
)


def write_poses_csv(path: Path, stack: Stack, result: BatchResult) -> None:
    """One row per chip deposited up to ``result.batch``."""
    n = len(result.positions)
    half = stack.target_size_mm / 2
    inside = (np.abs(result.positions[:, :2]) <= half).all(axis=1)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(POSE_COLUMNS)
        for i in range(n):
            x, y, z = result.positions[i]
            qx, qy, qz, qw = result.quaternions[i]
            writer.writerow(
                [
                    i,
                    int(stack.batch[i]),
                    stack.shapes[stack.shape_index[i]].name,
                    f"{x:.6f}",
                    f"{y:.6f}",
                    f"{z:.6f}",
                    f"{qx:.9f}",
                    f"{qy:.9f}",
                    f"{qz:.9f}",
                    f"{qw:.9f}",
                    int(inside[i]),
                ]
            )


def write_contacts_csv(path: Path, result: BatchResult) -> None:
    """One row per contact point; ``chip_b`` = -1 is the ground; the normal is on b, towards a."""
    c = result.contacts
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CONTACT_COLUMNS)
        for k in range(len(c)):
            writer.writerow(
                [
                    int(c.chip_a[k]),
                    int(c.chip_b[k]),
                    *(f"{v:.6f}" for v in c.point_a[k]),
                    *(f"{v:.6f}" for v in c.point_b[k]),
                    *(f"{v:.9f}" for v in c.normal[k]),
                    f"{c.distance[k]:.6f}",
                ]
            )


DROP_COLUMNS = (
    "drop",
    "shape",
    "x_mm",
    "y_mm",
    "z_mm",
    "qx",
    "qy",
    "qz",
    "qw",
    "tilt_x_rad",
    "tilt_y_rad",
    "distance_mm",
    "settled",
)


def write_drops_csv(path: Path, drops) -> None:
    """One row per drop of a :class:`packing.drop.DropResult`: final pose and release tilts."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(DROP_COLUMNS)
        for k in range(drops.n_drops):
            x, y, z = drops.positions[k]
            writer.writerow(
                [k, drops.shapes[k].name, repr(float(x)), repr(float(y)), repr(float(z))]
                + [repr(float(v)) for v in drops.quaternions[k]]
                + [repr(float(v)) for v in drops.tilts_rad[k]]
                + [repr(float(np.hypot(x, y))), int(bool(drops.settled[k]))]
            )
