"""The layout: Coordination Ring's one-cell-wide ring and the moves between its stations, from the layout in
ocv2/layouts.py parsed as text."""

from __future__ import annotations

import ast
import functools
import math

import numpy as np

from .folders import LAYOUTS


@functools.cache
def coord_ring_moves() -> dict:
    """Moves along Coordination Ring's one-cell-wide ring between the cells where an agent works each
    station, clockwise and counter-clockwise as the layout is drawn (y down; clockwise = rising
    atan2(y - cy, x - cx) about the centre counter, as ring_direction.py counts it)."""
    tree = ast.parse(LAYOUTS.read_text())
    text = None
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == "coord_ring":
                    text = ast.literal_eval(value)[0]
    grid = text.split("\n")
    floor = [(x, y) for y, row in enumerate(grid) for x, c in enumerate(row) if c in " A"]
    cx = np.mean([x for x, _ in floor])
    cy = np.mean([y for _, y in floor])
    ring_cells = sorted(floor, key=lambda p: math.atan2(p[1] - cy, p[0] - cx))
    index = {cell: i for i, cell in enumerate(ring_cells)}

    def work_cell(chars):
        cells = {
            (x + dx, y + dy)
            for y, row in enumerate(grid)
            for x, c in enumerate(row)
            if c in chars
            for dx, dy in ((0, 1), (1, 0), (0, -1), (-1, 0))
            if (x + dx, y + dy) in index
        }
        (cell,) = cells  # every station of this layout is worked from one ring cell
        return index[cell]

    n = len(ring_cells)
    station = {"plate": work_cell("B"), "pot": work_cell("P"), "serve": work_cell("X"), "onion": work_cell("O0")}

    def moves(a, b):
        clockwise = (station[b] - station[a]) % n
        return clockwise, n - clockwise

    legs = [("plate", "pot"), ("pot", "serve"), ("serve", "plate")]
    cycle_cw = sum(moves(a, b)[0] for a, b in legs)
    cycle_ccw = sum(moves(a, b)[1] for a, b in legs)
    return {
        "legs": [moves(a, b) for a, b in legs],
        "onion_pot": moves("onion", "pot"),
        "cycle": (cycle_cw, cycle_ccw),
        "ring": n,
    }
