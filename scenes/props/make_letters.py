#!/usr/bin/env python3
"""Writes the block letters of scenes/letters.toml as OBJ meshes: letter_m.obj, letter_w.obj,
letter_b.obj (run from anywhere; files go beside this script).

Each letter is drawn on a grid of square cells (rows below, "X" = solid) and extruded along z.
The surface is the boundary of the union of the cells: a front and a back face per solid cell,
and a side face wherever a solid cell borders an empty one. Every corner is shared by the faces
that meet there, so the mesh is closed and manifold (no two cells may touch at a corner only:
the glyphs avoid that), wound counter-clockwise seen from outside, as mwb-mesh requires of a
dynamic body. "B" has two holes: its convex hull would fill them, its convex decomposition
keeps them, which is why dynamic meshes are decomposed.
"""

import os

CELL = 0.08   # m, side of one cell
DEPTH = 0.06  # m, thickness of the extruded letter

GLYPHS = {
    "m": ["XX.XX",
          "XXXXX",
          "X.X.X",
          "X...X",
          "X...X"],
    "w": ["X...X",
          "X...X",
          "X.X.X",
          "XXXXX",
          "XX.XX"],
    "b": ["XXX.",
          "X.X.",
          "XXXX",
          "X..X",
          "XXXX"],
}


def letter_obj(rows):
    h, w = len(rows), len(rows[0])
    solid = {(c, r) for r, row in enumerate(rows) for c, ch in enumerate(row) if ch == "X"}
    # Grid corner (i, j, k) → position; i along x, j along y (row 0 on top), k = 0 back, 1 front.
    # Centred on the origin.
    def pos(i, j, k):
        return ((i - w / 2) * CELL, (h / 2 - j) * CELL, (k - 0.5) * DEPTH)

    index, verts, faces = {}, [], []

    def v(i, j, k):
        key = (i, j, k)
        if key not in index:
            verts.append(pos(i, j, k))
            index[key] = len(verts)  # OBJ indices are 1-based
        return index[key]

    def quad(*corners):
        faces.append([v(*c) for c in corners])

    for (c, r) in sorted(solid):
        # Cell spans corners i in [c, c+1], j in [r, r+1] (j grows downwards in y).
        quad((c, r + 1, 1), (c + 1, r + 1, 1), (c + 1, r, 1), (c, r, 1))  # front, +z
        quad((c, r + 1, 0), (c, r, 0), (c + 1, r, 0), (c + 1, r + 1, 0))  # back, -z
        if (c, r - 1) not in solid:  # top, +y
            quad((c, r, 0), (c, r, 1), (c + 1, r, 1), (c + 1, r, 0))
        if (c, r + 1) not in solid:  # bottom, -y
            quad((c, r + 1, 0), (c + 1, r + 1, 0), (c + 1, r + 1, 1), (c, r + 1, 1))
        if (c - 1, r) not in solid:  # left, -x
            quad((c, r, 0), (c, r + 1, 0), (c, r + 1, 1), (c, r, 1))
        if (c + 1, r) not in solid:  # right, +x
            quad((c + 1, r, 0), (c + 1, r, 1), (c + 1, r + 1, 1), (c + 1, r + 1, 0))

    out = ["# block letter extruded by make_letters.py: %d cells of %g m, %g m deep"
           % (len(solid), CELL, DEPTH)]
    out += ["v %.6g %.6g %.6g" % p for p in verts]
    out += ["f " + " ".join(str(i) for i in f) for f in faces]
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    here = os.path.dirname(os.path.abspath(__file__))
    for name, rows in GLYPHS.items():
        path = os.path.join(here, "letter_%s.obj" % name)
        with open(path, "w") as f:
            f.write(letter_obj(rows))
        print(path)
