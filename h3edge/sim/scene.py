"""The procedural indoor room: textured planar surfaces -> one mesh, a texture atlas and a GT mesh.

Two layouts. ``room`` (the default scene): 6 x 5 x 2.8 m (x east, y north, z up; floor at z = 0)
with weak-textured walls and ceiling, striped surfaces (floor planks, window blinds, a tiled
splash-back, book spines, a striped bin), photographs and tinted stone textures (posters, a brick
feature wall, a rug, cardboard boxes) and furniture that occludes (table, bookshelf, cabinet,
boxes, bin). ``studio`` (a second scene that differs in textures, layout and, with its own
trajectory, camera path): 7 x 4.5 x 3 m, see :func:`_studio_surfaces`. ``loft`` (the photographic
scene, walked through at a hand-held camera's pace): 5 x 4.2 x 2.7 m, see :func:`_loft_surfaces`.
``build_room(seed, layout=...)`` is a pure function of its arguments.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh

from h3edge.geometry.raycast import TextureAtlas
from h3edge.sim import textures as tx

ROOM_SIZE = np.array([6.0, 5.0, 2.8])
STUDIO_SIZE = np.array([7.0, 4.5, 3.0])
LOFT_SIZE = np.array([5.0, 4.2, 2.7])
MIP_LEVELS = 4
_ALIGN = 1 << (MIP_LEVELS - 1)  # atlas cells start on multiples of this, so mips stay aligned
_LIGHT = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])


@dataclass
class Quad:
    """Planar rectangle o, o+a, o+a+b, o+b whose visible side faces a x b; texture x runs along a."""

    o: np.ndarray
    a: np.ndarray
    b: np.ndarray
    uv0: tuple[float, float] = (0.0, 0.0)  # fraction of the surface texture at o
    uv1: tuple[float, float] = (1.0, 1.0)  # fraction at o + a + b

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.a, self.b)
        return n / np.linalg.norm(n)


@dataclass
class Surface:
    name: str
    texture: np.ndarray  # uint8 (h, w, 3)
    texel: float  # metres per texel
    quads: list[Quad]
    kind: str  # weak | stripes | rich: the texture class it was designed as


@dataclass
class Box:
    lo: np.ndarray
    hi: np.ndarray


@dataclass
class Room:
    """The built scene: render mesh + atlas, and the solid obstacles a camera must stay out of."""

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int32
    atlas: TextureAtlas
    face_surface: np.ndarray  # (F,) index into surface_names
    surface_names: list[str]
    surface_kinds: list[str]
    obstacles: list[Box] = field(default_factory=list)
    bounds: np.ndarray = field(default_factory=lambda: np.stack([np.zeros(3), ROOM_SIZE]))
    gt_mesh: trimesh.Trimesh | None = None


def _quad(o, a, b, uv0=(0.0, 0.0), uv1=(1.0, 1.0)) -> Quad:
    return Quad(np.asarray(o, float), np.asarray(a, float), np.asarray(b, float), uv0, uv1)


def _surface(name, texture, texel, quads, kind) -> Surface:
    return Surface(name, texture, texel, quads, kind)


def _tex_size(quad: Quad, texel: float) -> tuple[int, int]:
    return max(8, int(np.ceil(np.linalg.norm(quad.b) / texel))), max(8, int(np.ceil(np.linalg.norm(quad.a) / texel)))


def _box_quads(lo, hi, skip_bottom=True) -> dict[str, Quad]:
    """Outward-facing quads of an axis-aligned box, keyed by face name."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    dx, dy, dz = hi - lo
    X, Y, Z = np.array([dx, 0, 0]), np.array([0, dy, 0]), np.array([0, 0, dz])
    q = {
        "-x": _quad(lo + Y, -Y, Z),
        "+x": _quad(lo + X, Y, Z),
        "-y": _quad(lo, X, Z),
        "+y": _quad(lo + X + Y, -X, Z),
        "+z": _quad(lo + Z, X, Y),
    }
    if not skip_bottom:
        q["-z"] = _quad(lo + Y, X, -Y)
    return q


def _shelf_front(rng, h, w) -> np.ndarray:
    """Bookshelf front: wooden boards with rows of book spines between them."""
    img = tx.planks(rng, h, w, plank_px=max(8, h))  # wood tone
    rows = 4
    board = max(4, h // 40)
    row_h = (h - board) // rows
    for r in range(rows):
        y0 = board + r * row_h
        books_h = row_h - board
        img[y0:y0 + books_h, board:w - board] = tx.book_spines(rng, books_h, w - 2 * board)
    return img


def _cylinder_quads(center, radius, height, segments=24) -> list[Quad]:
    quads = []
    for i in range(segments):
        t0, t1 = 2 * np.pi * i / segments, 2 * np.pi * (i + 1) / segments
        p0 = np.array([center[0] + radius * np.cos(t0), center[1] + radius * np.sin(t0), 0.0])
        p1 = np.array([center[0] + radius * np.cos(t1), center[1] + radius * np.sin(t1), 0.0])
        quads.append(_quad(p0, p1 - p0, [0, 0, height], (i / segments, 0.0), ((i + 1) / segments, 1.0)))
    return quads


class _Builder:
    """Collects surfaces (texture sized from the quads and texel) and the solid obstacles."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.surfaces: list[Surface] = []
        self.obstacles: list[Box] = []

    def add(self, name, quads, texel, kind, make) -> None:
        quads = quads if isinstance(quads, list) else [quads]
        # texture covers the union of the quads' uv ranges: size it from the first quad and the uv span
        q0 = quads[0]
        span_u = max(q.uv1[0] for q in quads) - min(q.uv0[0] for q in quads)
        h, w0 = _tex_size(q0, texel)
        w = max(8, int(np.ceil(w0 * span_u / max(q0.uv1[0] - q0.uv0[0], 1e-9))))
        self.surfaces.append(_surface(name, make(h, w), texel, quads, kind))

    def box(self, name, lo, hi, texel, kind, make, faces=None) -> None:
        """An axis-aligned solid box; ``kind`` and ``make`` are functions of the face name."""
        self.obstacles.append(Box(np.asarray(lo, float), np.asarray(hi, float)))
        for fname, q in _box_quads(lo, hi).items():
            if faces is None or fname in faces:
                self.add(f"{name}{fname}", q, texel, kind(fname) if callable(kind) else kind, make(fname))

    def table(self, name, lo, hi, texel, make) -> None:
        """A plank top from ``lo`` to ``hi`` (top texel ``texel``) on four 5 cm legs (4 mm texels)
        set 5 cm in from its corners, as ``<name>_top`` and ``<name>_leg0..3``."""
        self.box(f"{name}_top", lo, hi, texel, "stripes", make)
        x0, y0 = round(lo[0] + 0.05, 6), round(lo[1] + 0.05, 6)
        x1, y1 = round(hi[0] - 0.1, 6), round(hi[1] - 0.1, 6)
        for i, (x, y) in enumerate([(x0, y0), (x1, y0), (x0, y1), (x1, y1)]):
            self.box(f"{name}_leg{i}", [x, y, 0.0], [x + 0.05, y + 0.05, lo[2]], 0.004, "stripes", make)

    def cylinder(self, name, center, radius, height, texel, kind, make) -> None:
        self.obstacles.append(Box(np.array([center[0] - radius, center[1] - radius, 0.0]),
                                  np.array([center[0] + radius, center[1] + radius, height])))
        self.add(name, _cylinder_quads(center, radius, height), texel, kind, make)

    def shell(self, size, textures: dict) -> None:
        """Floor, ceiling and four walls of a size[0] x size[1] x size[2] room, visible sides inwards;
        ``textures``: {name: (texel, kind, make)}."""
        W, D, H = size
        quads = {"floor": _quad([0, D, 0], [W, 0, 0], [0, -D, 0]), "ceiling": _quad([0, 0, H], [W, 0, 0], [0, D, 0]),
                 "wall_south": _quad([0, 0, H], [W, 0, 0], [0, 0, -H]),
                 "wall_east": _quad([W, 0, H], [0, D, 0], [0, 0, -H]),
                 "wall_north": _quad([W, D, H], [-W, 0, 0], [0, 0, -H]),
                 "wall_west": _quad([0, D, H], [0, -D, 0], [0, 0, -H])}
        for name, q in quads.items():
            texel, kind, make = textures[name]
            self.add(name, q, texel, kind, make)


def _surfaces(rng: np.random.Generator) -> tuple[list[Surface], list[Box]]:
    """The default room (``ROOM_SIZE``)."""
    b = _Builder(rng)
    add, box = b.add, b.box
    W, D, H = ROOM_SIZE
    b.shell(ROOM_SIZE, {
        "floor": (0.004, "stripes", lambda h, w: tx.planks(rng, h, w, 40)),
        "ceiling": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (236, 234, 228))),
        "wall_south": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (196, 204, 212))),
        "wall_east": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (214, 200, 176))),
        "wall_north": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (222, 218, 206))),
        "wall_west": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (190, 208, 186)))})
    # wall decorations, a little proud of the wall
    add(
        "blinds",
        _quad([1.5, 0.03, 2.3], [2.0, 0, 0], [0, 0, -1.4]),
        0.003,
        "stripes",
        lambda h, w: tx.blinds(rng, h, w, 14),
    )
    add(
        "tiles",
        _quad([5.8, D - 0.01, 1.6], [-2.2, 0, 0], [0, 0, -0.7]),
        0.003,
        "stripes",
        lambda h, w: tx.tiles(rng, h, w, 50, 3),
    )
    add("brick_wall", _quad([2.4, D - 0.01, H], [-2.0, 0, 0], [0, 0, -H]), 0.004, "rich",
        lambda h, w: tx.tinted(rng, "brick", h, w, (1.0, 0.62, 0.48), 256))
    for name, corner, across, down, photo in (  # photographs on the walls
        ("poster_astronaut", [W - 0.01, 2.9, 2.0], [0, 1.0, 0], [0, 0, -1.0], "astronaut"),
        ("poster_coffee", [3.2, D - 0.01, 2.3], [-0.7, 0, 0], [0, 0, -0.47], "coffee"),
        ("poster_chelsea", [0.01, 3.8, 2.0], [0, -0.9, 0], [0, 0, -0.6], "chelsea"),
        ("poster_rocket", [0.01, 2.5, 2.1], [0, -0.9, 0], [0, 0, -0.6], "rocket"),
        ("poster_hubble", [0.01, 1.3, 1.9], [0, -0.8, 0], [0, 0, -0.7], "hubble_deep_field"),
    ):
        add(name, _quad(corner, across, down), 0.003, "rich", lambda h, w, p=photo: tx.photo(p, h, w))
    add("rug", _quad([2.0, 3.7, 0.008], [2.6, 0, 0], [0, -2.0, 0]), 0.004, "rich",
        lambda h, w: tx.tinted(rng, "gravel", h, w, (0.75, 0.55, 0.5), 300))

    wood = lambda f: (lambda h, w: tx.planks(rng, h, w, 24))  # noqa: E731
    b.table("table", [2.4, 2.2, 0.72], [3.8, 3.2, 0.76], 0.004, wood)
    # bookshelf against the east wall: its front (-x) shows the books
    box("shelf", [5.6, 1.0, 0.0], [5.98, 2.6, 2.0], 0.004, lambda f: "stripes",
        lambda f: (lambda h, w: _shelf_front(rng, h, w)) if f == "-x" else (lambda h, w: tx.planks(rng, h, w, 30)))
    # white cabinet in the north-west corner, a cardboard box on top
    box(
        "cabinet",
        [0.05, 3.6, 0.0],
        [0.55, 4.9, 0.9],
        0.008,
        "weak",
        lambda f: lambda h, w: tx.weak(rng, h, w, (240, 240, 236), 2.0),
    )
    cardboard = lambda f: (lambda h, w: tx.tinted(rng, "gravel", h, w, (0.85, 0.68, 0.45), 200))  # noqa: E731
    box("box_top", [0.1, 3.8, 0.9], [0.45, 4.3, 1.2], 0.004, "rich", cardboard)
    box("box_floor", [1.0, 1.0, 0.0], [1.5, 1.4, 0.4], 0.004, "rich", cardboard)
    # striped cylindrical bin near the north-east corner
    b.cylinder("bin", (4.8, 4.3), 0.18, 0.45, 0.003, "stripes",
               lambda h, w: np.transpose(tx.blinds(rng, w, h, 20), (1, 0, 2)).copy())
    return b.surfaces, b.obstacles


def _studio_surfaces(rng: np.random.Generator) -> tuple[list[Surface], list[Box]]:
    """The second scene (``STUDIO_SIZE``), built to differ from the default room in every texture
    and in layout: a terracotta tiled floor, a full grey brick wall, vertical blinds, plank
    cladding, a wall of photographic tiles, a notice board of printed text, a sofa in woven fabric,
    a gravel planter, a concrete column, a desk and crates, plain white walls and ceiling."""
    b = _Builder(rng)
    add, box = b.add, b.box
    W, D, H = STUDIO_SIZE
    b.shell(STUDIO_SIZE, {
        "floor": (0.005, "stripes", lambda h, w: tx.tiles(rng, h, w, 90, 4, base=(176, 98, 70))),
        "ceiling": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (242, 242, 240))),
        "wall_south": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (238, 236, 230))),
        "wall_east": (0.004, "rich", lambda h, w: tx.tinted(rng, "brick", h, w, (0.78, 0.78, 0.82), 220)),
        "wall_north": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (226, 230, 236))),
        "wall_west": (0.004, "stripes", lambda h, w: np.transpose(tx.planks(rng, w, h, 30), (1, 0, 2)).copy())})
    # north wall: vertical blinds over a window, a wall of photographic tiles, a notice board
    add("blinds", _quad([0.6, D - 0.02, 2.5], [2.2, 0, 0], [0, 0, -1.9]), 0.003, "stripes",
        lambda h, w: np.transpose(tx.blinds(rng, w, h, 16), (1, 0, 2)).copy())
    add(
        "photo_tiles",
        _quad([6.4, D - 0.01, 2.2], [-2.4, 0, 0], [0, 0, -1.6]),
        0.003,
        "rich",
        lambda h, w: tx.photo_tiles(
            rng, h, w, ["immunohistochemistry", "retina", "colorwheel", "coffee", "chelsea"], 6
        ),
    )
    add("notice_board", _quad([0.02, 1.6, 1.9], [0, -1.0, 0], [0, 0, -0.8]), 0.002, "rich",
        lambda h, w: tx.tinted(rng, "text", h, w, (1.0, 0.97, 0.9), 240))
    add("poster_rocket", _quad([W - 0.01, 0.8, 2.1], [0, 0.8, 0], [0, 0, -1.1]), 0.003, "rich",
        lambda h, w: tx.photo("rocket", h, w))
    add("carpet", _quad([3.0, 2.6, 0.008], [2.2, 0, 0], [0, -1.6, 0]), 0.004, "rich",
        lambda h, w: tx.tinted(rng, "grass", h, w, (0.45, 0.55, 0.8), 260))
    fabric = lambda f: (lambda h, w: tx.tinted(rng, "grass", h, w, (0.8, 0.5, 0.4), 160))  # noqa: E731
    box("sofa_seat", [3.2, 0.2, 0.0], [5.4, 1.0, 0.45], 0.004, "rich", fabric)
    box("sofa_back", [3.2, 0.05, 0.0], [5.4, 0.25, 0.9], 0.004, "rich", fabric, faces=["+y", "+z", "-x", "+x"])
    wood = lambda f: (lambda h, w: tx.planks(rng, h, w, 18))  # noqa: E731
    b.table("desk", [0.4, 2.6, 0.74], [1.9, 3.4, 0.78], 0.003, wood)
    crate = lambda f: (lambda h, w: tx.planks(rng, h, w, 22))  # noqa: E731
    box("crate_a", [6.0, 1.6, 0.0], [6.6, 2.2, 0.5], 0.004, "stripes", crate)
    box("crate_b", [6.1, 1.7, 0.5], [6.5, 2.1, 0.85], 0.004, "stripes", crate)
    gravel = lambda f: (lambda h, w: tx.tinted(rng, "gravel", h, w, (0.7, 0.75, 0.6), 180))  # noqa: E731
    box("planter", [2.4, 3.7, 0.0], [3.6, 4.2, 0.35], 0.004, "rich", gravel)
    b.cylinder("column", (4.6, 2.9), 0.22, H, 0.004, "rich",
               lambda h, w: tx.tinted(rng, "coins", h, w, (0.9, 0.88, 0.84), 200))
    box("cabinet", [6.4, 3.0, 0.0], [6.95, 4.0, 1.1], 0.008, "weak",
        lambda f: (lambda h, w: tx.weak(rng, h, w, (60, 64, 72), 2.0)))
    return b.surfaces, b.obstacles


def _loft_surfaces(rng: np.random.Generator) -> tuple[list[Surface], list[Box]]:
    """The photographic scene (``LOFT_SIZE``): nearly every surface a scikit-image photograph or
    photographic texture (CC0) at 2-4 mm a texel, finer than a 1 cm cell: a brick wall, a gravel
    floor, a grass rug, a wall of photographs, a mosaic of micrographs, a stereo photograph of a
    motorcycle, printed text, a coin-embossed column, crates in stone; plus plain painted walls
    and ceiling and one plank table, as a flat has."""
    b = _Builder(rng)
    add, box = b.add, b.box
    W, D, H = LOFT_SIZE
    b.shell(LOFT_SIZE, {
        "floor": (0.004, "rich", lambda h, w: tx.tinted(rng, "gravel", h, w, (0.82, 0.78, 0.72), 280)),
        "ceiling": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (238, 238, 234))),
        "wall_south": (0.004, "rich", lambda h, w: tx.tinted(rng, "brick", h, w, (1.0, 0.58, 0.45), 240)),
        "wall_east": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (206, 214, 222))),
        "wall_north": (0.01, "weak", lambda h, w: tx.weak(rng, h, w, (228, 220, 204))),
        "wall_west": (0.004, "rich", lambda h, w: tx.tinted(rng, "grass", h, w, (0.55, 0.62, 0.5), 200))})
    for name, corner, across, down, photo in (  # photographs on the plain walls
        ("photo_motorcycle", [W - 0.01, 0.5, 2.0], [0, 1.3, 0], [0, 0, -0.88], "motorcycle"),
        ("photo_astronaut", [W - 0.01, 2.2, 1.9], [0, 0.8, 0], [0, 0, -0.8], "astronaut"),
        ("photo_coffee", [W - 0.01, 3.2, 1.7], [0, 0.75, 0], [0, 0, -0.5], "coffee"),
        ("photo_hubble", [3.9, D - 0.01, 2.1], [-1.1, 0, 0], [0, 0, -0.96], "hubble_deep_field"),
        ("photo_chelsea", [2.4, D - 0.01, 1.8], [-0.75, 0, 0], [0, 0, -0.5], "chelsea"),
        ("photo_camera", [1.4, D - 0.01, 2.0], [-0.8, 0, 0], [0, 0, -0.8], "camera"),
    ):
        add(name, _quad(corner, across, down), 0.0025, "rich", lambda h, w, p=photo: tx.photo(p, h, w))
    add("mosaic", _quad([3.9, D - 0.01, 0.85], [-2.8, 0, 0], [0, 0, -0.6]), 0.0025, "rich",
        lambda h, w: tx.photo_tiles(rng, h, w, ["immunohistochemistry", "retina", "colorwheel", "rocket"], 10))
    add("newspaper", _quad([0.01, 3.4, 1.8], [0, -1.2, 0], [0, 0, -0.7]), 0.002, "rich",
        lambda h, w: np.ascontiguousarray(tx.tinted(rng, "page", h, w, (1.0, 0.96, 0.88), 300)[:, ::-1]))  # reads
    add("rug", _quad([1.5, 2.9, 0.008], [2.2, 0, 0], [0, -1.6, 0]), 0.004, "rich",
        lambda h, w: tx.tinted(rng, "grass", h, w, (0.55, 0.75, 0.45), 220))
    wood = lambda f: (lambda h, w: tx.planks(rng, h, w, 20))  # noqa: E731
    b.table("table", [1.9, 1.7, 0.72], [3.1, 2.5, 0.76], 0.003, wood)
    stone = lambda f: (lambda h, w: tx.tinted(rng, "gravel", h, w, (0.7, 0.66, 0.8), 160))  # noqa: E731
    box("crate_a", [4.2, 3.3, 0.0], [4.9, 4.1, 0.55], 0.003, "rich", stone)
    box("crate_b", [0.1, 0.2, 0.0], [0.7, 0.8, 0.7], 0.003, "rich",
        lambda f: (lambda h, w: tx.tinted(rng, "brick", h, w, (0.8, 0.8, 0.85), 150)))
    b.cylinder("column", (3.9, 0.9), 0.18, H, 0.003, "rich",
               lambda h, w: tx.tinted(rng, "coins", h, w, (0.95, 0.85, 0.7), 180))
    return b.surfaces, b.obstacles


def _shade(normal: np.ndarray) -> float:
    """Baked, view-independent Lambertian shading so that differently oriented faces differ."""
    return float(0.78 + 0.22 * np.dot(normal, _LIGHT))


LAYOUTS = {"room": (ROOM_SIZE, _surfaces), "studio": (STUDIO_SIZE, _studio_surfaces),
           "loft": (LOFT_SIZE, _loft_surfaces)}


def build_room(seed: int, gt_spacing: float = 0.05, layout: str = "room") -> Room:
    """Build the ``layout`` ("room", "studio" or "loft") for ``seed``: mesh, mip-mapped atlas and the
    vertex-coloured GT mesh."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose from {sorted(LAYOUTS)}")
    size, builder = LAYOUTS[layout]
    rng = np.random.default_rng(seed)
    surfaces, obstacles = builder(rng)

    # shade each surface once (all quads of a surface share an orientation class except the bin)
    for s in surfaces:
        if len(s.quads) == 1:
            s.texture = np.clip(s.texture.astype(np.float32) * _shade(s.quads[0].normal), 0, 255).astype(np.uint8)

    # shelf-pack padded textures into the atlas
    atlas_w = 4096
    cells, x, y, row_h = [], 0, 0, 0
    for s in sorted(range(len(surfaces)), key=lambda i: -surfaces[i].texture.shape[0]):
        h, w = surfaces[s].texture.shape[:2]
        ch, cw = -(-(h + 2 * _ALIGN) // _ALIGN) * _ALIGN, -(-(w + 2 * _ALIGN) // _ALIGN) * _ALIGN
        if cw > atlas_w:
            raise ValueError(f"texture of {surfaces[s].name} is wider than the atlas")
        if x + cw > atlas_w:
            x, y, row_h = 0, y + row_h, 0
        cells.append((s, x, y, ch, cw))
        x, row_h = x + cw, max(row_h, ch)
    atlas_h = y + row_h
    atlas0 = np.zeros((atlas_h, atlas_w, 3), np.uint8)
    origin = {}
    for s, cx, cy, ch, cw in cells:
        t = surfaces[s].texture
        h, w = t.shape[:2]
        padded = cv2.copyMakeBorder(t, _ALIGN, ch - h - _ALIGN, _ALIGN, cw - w - _ALIGN, cv2.BORDER_REPLICATE)
        atlas0[cy:cy + ch, cx:cx + cw] = padded
        origin[s] = (cx + _ALIGN, cy + _ALIGN)
    levels = [atlas0]
    for _ in range(1, MIP_LEVELS):
        prev = levels[-1]
        levels.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))

    verts, faces, face_uv, face_texel, face_surf = [], [], [], [], []
    for si, s in enumerate(surfaces):
        ox, oy = origin[si]
        h, w = s.texture.shape[:2]
        for q in s.quads:
            base = len(verts)
            verts += [q.o, q.o + q.a, q.o + q.a + q.b, q.o + q.b]
            u0, v0 = ox + q.uv0[0] * w, oy + q.uv0[1] * h
            u1, v1 = ox + q.uv1[0] * w, oy + q.uv1[1] * h
            uv = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
            for tri in ((0, 1, 2), (0, 2, 3)):
                faces.append([base + k for k in tri])
                face_uv.append([uv[k] for k in tri])
                face_texel.append(s.texel)
                face_surf.append(si)
    atlas = TextureAtlas(levels, np.asarray(face_uv, np.float32), np.asarray(face_texel, np.float32))
    room = Room(np.asarray(verts, np.float32), np.asarray(faces, np.int32), atlas, np.asarray(face_surf, np.int32),
                [s.name for s in surfaces], [s.kind for s in surfaces], obstacles,
                np.stack([np.zeros(3), np.asarray(size, float)]))
    room.gt_mesh = _gt_mesh(surfaces, gt_spacing)
    return room


def _gt_mesh(surfaces: list[Surface], spacing: float) -> trimesh.Trimesh:
    """Each quad tessellated to <= ``spacing`` cells, vertex colours from the blurred texture."""
    all_v, all_f, all_c = [], [], []
    n = 0
    for s in surfaces:
        h, w = s.texture.shape[:2]
        sigma = max(0.5, 0.5 * spacing / s.texel)
        blurred = cv2.GaussianBlur(s.texture, (0, 0), sigma)
        for q in s.quads:
            nu = max(1, int(np.ceil(np.linalg.norm(q.a) / spacing)))
            nv = max(1, int(np.ceil(np.linalg.norm(q.b) / spacing)))
            su, sv = np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1)
            uu, vv = np.meshgrid(su, sv)  # (nv+1, nu+1)
            p = q.o + uu[..., None] * q.a + vv[..., None] * q.b
            tu = (q.uv0[0] + uu * (q.uv1[0] - q.uv0[0])) * w
            tv = (q.uv0[1] + vv * (q.uv1[1] - q.uv0[1])) * h
            xi = np.clip(tu.astype(int), 0, w - 1)
            yi = np.clip(tv.astype(int), 0, h - 1)
            col = blurred[yi, xi]
            idx = np.arange((nv + 1) * (nu + 1)).reshape(nv + 1, nu + 1) + n
            a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
            all_f.append(
                np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            )
            all_v.append(p.reshape(-1, 3))
            all_c.append(col.reshape(-1, 3))
            n += p.shape[0] * p.shape[1]
    colors = np.concatenate(all_c)
    rgba = np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(np.concatenate(all_v), np.concatenate(all_f), vertex_colors=rgba, process=False)
