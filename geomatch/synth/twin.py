"""A synthetic trap for Structure-from-Motion: one building whose opposite facades look alike.

Why: on a real courtyard (castle-P19) the opposite facades share their architecture (the same
rows of windows) but not their details (doors, the ground floor, weathering, things in front).
LightGlue matches views of such look-alike facades that share nothing with up to a few hundred
geometrically consistent inliers, a fraction of a right neighbour pair's. The pairs pass two-view
verification, and because the look-alike is a symmetry of the building they also agree with each
other, so a triangle check over the view graph finds the loops among them consistent, and
COLMAP's incremental mapper builds one confident model with a block of cameras turned about 180
degrees. The scenes of :mod:`geomatch.synth.aerial` give every surface its own texture precisely to avoid
this; here it is built on purpose, so that a filter against it can be tested against ground truth.

The building is one box at the origin, 10 m east-west, 7 m north-south, 6 m high. The upper half
of its north (+y) and south (-y) faces carries the same texture (the repeated windows), laid so
that it reads the same from outside: a 180 degree rotation about the vertical axis maps one band
onto the other, so a view of the north band matches a view of the south band texel for texel with
a consistent (wrong) relative pose, that of the south camera turned 180 degrees about the building
onto the north side. The rest of each long face is its own: the lower half (the ground floor) and
the outer 15% of its length (the corners) carry a texture of that face only, as do the east and
west faces and the ground. So the look-alike pairs match on the band alone, while right neighbours
match on everything they both see.

Cameras stand on a ring of 16 m radius at eye level, each looking at the building's lower half
near its centre. The ring's centre is 2 m east of the building's, so no view has an exact mirror
twin across the building: the 180 degree rotation maps the ring onto one centred 2 m west, and the
look-alike pairs see the band from positions 4 m apart along it, not as a duplicate image. With 14
cameras (26 degrees apart) the two on the east-west axis see an end face only, their neighbours an
end face and a long face, so every view has right pairs with the views on either side and the
chain of right pairs goes round both ends of the building.

With ``geomatch run``'s defaults (method ``auto``: ALIKED + LightGlue for these ground views;
exhaustive pairs) about half the verified pairs are wrong: those between north and south views,
through the band, with a fraction of a ring neighbour pair's inliers, and weak ones of the two
end-on views. With nothing filtering, a block of north views is turned onto the south side; the
triangle loop check alone keeps many wrong pairs and drops right ones. With the spanning-tree
check beside it (the default: the loop check may not drop a tree pair) no wrong pair reaches the
mapper and every camera comes out right. Both checks also drop a few right pairs: for one link of
the tree (an end-on view and its neighbour) the tree takes the essential matrix's rotation where
COLMAP's pose is right (its triangles close for every candidate, and a tie goes to the first), so
the right pairs across that link disagree with the tree; the mapper does without them. Other seeds
and method ``sparse`` end the same way. tests/test_twin_scene.py checks the default run and the
run without the checks.

Output of :func:`write_twin_scene`: ``images/`` (PNG with the EXIF of :func:`geomatch.synth.sensors.save_png`)
and ``gt/`` (COLMAP text model), as :func:`geomatch.synth.aerial.write_scene` writes them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .aerial import Box, Scene
from .camera import Camera, look_at
from .groundtruth import write_gt
from .photos import photo
from .sensors import save_png
from .texture import TEXTURES, unique_texture

# the building (metres): the long faces along x carry the look-alike band; near square, so that
# the views off its corners see an end face and a long face at workable angles
LENGTH, DEPTH, HEIGHT = 10.0, 7.0, 6.0  # along x, along y, up
SHARED_HEIGHT = 0.5  # the top fraction of the long faces that look alike: the repeated windows
END_MARGIN = 0.15  # the fraction of the long faces' length at each end that is each face's own
RING_RADIUS = 16.0
RING_CENTRE = (2.0, 0.0)  # off the building's centre: no view has an exact mirror twin
EYE_HEIGHT = 1.6
TEXTURE_PX = 768  # texels across a face's longer side: finer than the views sample it


def _face_texture(rng: np.random.Generator, name: str) -> np.ndarray:
    """A face of its own: a random crop of photo ``name``, colour-shifted and marked with shapes
    (corner-rich, so that the look-alike band gives the matcher plenty to be fooled by)."""
    src = photo(name)
    h, w = src.shape[:2]
    side = int(min(h, w) * rng.uniform(0.55, 0.8))
    y, x = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    return unique_texture(src[y : y + side, x : x + side], TEXTURE_PX, rng, shapes=150).astype(np.float32)


class TwinScene(Scene):
    """The textured ground of :class:`geomatch.synth.aerial.Scene` with the one building on it."""

    def __init__(self, seed: int) -> None:
        super().__init__(seed, n_boxes=0)
        rng = self.rng
        # every texture from a photo of its own: only the band is meant to repeat
        names = [str(n) for n in rng.choice(TEXTURES, 6, replace=False)]
        band, west, east, roof, south, north = (_face_texture(rng, n) for n in names)
        # a long face spans the texture's width and HEIGHT / LENGTH of its rows, top down. The
        # renderer lays a face's texture along +x on both y faces, which reads left to right from
        # the south and right to left from the north: the north copy of the band is mirrored, so
        # that both read the same from outside (the building's 180 degree symmetry)
        rows = round(SHARED_HEIGHT * HEIGHT / LENGTH * TEXTURE_PX)
        cols = slice(round(END_MARGIN * TEXTURE_PX), round((1 - END_MARGIN) * TEXTURE_PX))
        south[:rows, cols] = band[:rows, cols]
        north[:rows, cols] = band[:rows, ::-1][:, cols]
        first = len(self.textures)
        # faces -x, +x, -y, +y, -z, +z
        self.textures += [west, east, south, north, roof]
        faces = (first, first + 1, first + 2, first + 3, first + 4, first + 4)
        half = np.array([LENGTH / 2, DEPTH / 2, 0.0])
        self.boxes.append(Box(-half, half + np.array([0.0, 0.0, HEIGHT]), faces))

    def ring(self, n: int, width: int, height: int) -> list[Camera]:
        """``n`` cameras evenly around :data:`RING_CENTRE` from the east (azimuth 0, counter-
        clockwise), jittered by up to 3 degrees, 0.5 m out and 0.1 m up, each looking at a point of
        the building's lower half near its centre (a walker photographing the building)."""
        rng = self.rng
        f = 0.9 * width
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        cams = []
        for i in range(n):
            ang = 2 * np.pi * i / n + np.deg2rad(rng.uniform(-3, 3))
            r = RING_RADIUS + rng.uniform(-0.5, 0.5)
            C = np.array(
                [
                    RING_CENTRE[0] + r * np.cos(ang),
                    RING_CENTRE[1] + r * np.sin(ang),
                    EYE_HEIGHT + rng.uniform(-0.1, 0.1),
                ]
            )
            target = np.array([*rng.uniform(-1.0, 1.0, 2), rng.uniform(2.0, 3.0)])
            R, t = look_at(C, target)
            cams.append(Camera(f"ring_{i:02d}.png", K, R, t, width, height, False))
        return cams


def write_twin_scene(
    out: str | Path, cameras: int = 14, seed: int = 0, width: int = 480, height: int = 360
) -> list[Camera]:
    """Render the scene into ``out`` (images/, gt/) and return its cameras. The defaults are the
    scene tests/test_twin_scene.py runs (module docstring)."""
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    scene = TwinScene(seed)
    cams = scene.ring(cameras, width, height)
    for c in cams:
        img, _ = scene.render(c)
        save_png(out / "images" / c.name, img, c)
    write_gt(cams, out / "gt")
    return cams
