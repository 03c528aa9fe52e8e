"""ParaView opens files as its user does; prints what it found as JSON.

Run by ParaView's Python under a virtual X server (Debian's ParaView crashes in its
off-screen mode)::

    xvfb-run -a pvpython tests/clients/paraview_open.py FILE [FILE ...]

Each file is opened with ``paraview.simple.OpenDataFile`` (the reader ParaView's File >
Open picks) and its pipeline updated. Prints one JSON object, by path: ``reader`` (the
reader's label), ``cells`` and ``points`` (of the last time step), ``cell_arrays`` and
``point_arrays`` (names), ``ranges`` (each cell array's first-component range),
``time_steps`` (their count; 0 for a file without time) and ``bounds``.
"""

import json
import sys

from paraview import simple


def describe(path):
    """What ParaView reads from ``path``."""
    reader = simple.OpenDataFile(path)
    if reader is None:
        raise SystemExit(f"paraview_open: ParaView has no reader for {path}")
    times = list(getattr(reader, "TimestepValues", None) or [])
    reader.UpdatePipeline(times[-1] if times else 0.0)
    info = reader.GetDataInformation()
    cell_arrays = sorted(reader.CellData.keys())
    return {
        "reader": reader.GetXMLLabel(),
        "cells": info.GetNumberOfCells(),
        "points": info.GetNumberOfPoints(),
        "cell_arrays": cell_arrays,
        "point_arrays": sorted(reader.PointData.keys()),
        "ranges": {name: list(reader.CellData[name].GetRange(0)) for name in cell_arrays},
        "time_steps": len(times),
        "bounds": list(info.GetBounds()),
    }


if __name__ == "__main__":
    found = {path: describe(path) for path in sys.argv[1:]}
    sys.stdout.write(json.dumps(found) + "\n")
