"""Procedural indoor rooms made of axis-aligned boxes, deterministic by seed.

A scene is an axis-aligned room ``[0, Lx] x [0, Ly] x [0, Lz]`` (world frame, z up, metres; ``Ly >= Lx``) seen
from inside, plus furniture-like boxes: cabinets, tables (top and four legs), open shelves, box stacks,
pictures on the walls, a rug, a low table and a ceiling lamp. Furniture stands in a band along the walls or
stays low / near the ceiling, so that a *free region* in the middle keeps at least ``clearance`` metres to
every surface; trajectories and viewpoints are drawn inside it.

Faces: box ``b`` has faces ``6 * b + 2 * axis + side`` (``side`` 0 = the face at ``lo[axis]``, 1 = at
``hi[axis]``); box 0 is the room, seen from inside. A face's texture coordinates ``(u, v)`` run along the
world axes :data:`FACE_UV_AXES` ``[axis]`` from the box's ``lo`` corner (vertical faces: ``v`` is height).

The ``whitewall`` preset leaves the wall ``x = Lx`` (the large one, ``Ly`` wide) bare and textureless.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.textures import TextureAtlas, make_texture

__all__ = ["PRESETS", "ROOM_PRESETS", "FACE_UV_AXES", "Scene", "make_scene", "scene_from_boxes", "box_distance"]

PRESETS = ("textured", "whitewall", "flight", "handheld", "tabletop")
#: Presets of :mod:`sim.rooms` (natural textures, point light, realistic sensors by default).
ROOM_PRESETS = ("flight", "handheld", "tabletop")
#: (u axis, v axis) of faces normal to x, y, z.
FACE_UV_AXES = ((1, 2), (0, 2), (0, 1))
#: The textureless wall of the ``whitewall`` preset: (axis, side) -> the wall x = Lx.
WHITEWALL_FACE = (0, 1)


@dataclass
class Scene:
    """Geometry, textures and shading of one room.

    Attributes:
        size: (3,) room extent ``(Lx, Ly, Lz)`` [m].
        lo, hi: (B, 3) float64 box corners [m] in the world frame; box 0 is the room (seen from inside).
        names: (B,) box names (``room``, ``cabinet``, ``table_top``, ...).
        free_lo, free_hi: (3,) corners of the free region (positions there keep ``clearance`` to every
            surface).
        clearance: guaranteed distance [m] between the free region and every box (room walls included).
        atlas: per-face textures (RGB or grey albedo).
        shade: (6B,) float32 per-face shading factor (ambient + Lambert of a directional light).
        whitewall: True when the wall ``x = Lx`` is the textureless one.
        seed: the seed the scene was built from.
    """

    size: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    names: list[str]
    free_lo: np.ndarray
    free_hi: np.ndarray
    clearance: float
    atlas: TextureAtlas
    shade: np.ndarray
    whitewall: bool = False
    seed: int = 0
    light_dir: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    #: realistic rooms (:mod:`sim.rooms`): a point light for per-pixel shading (None: per-face ``shade`` only)
    point_light: np.ndarray | None = None
    light_range: float = 4.0
    #: (6B,) faces that glow (windows, lamps): ``shade`` only, no point-light shading
    emissive: np.ndarray | None = None
    preset: str = "textured"

    @property
    def n_boxes(self) -> int:
        return int(self.lo.shape[0])

    def min_distance(self, p_w: np.ndarray) -> np.ndarray:
        """Distance [m] from points (..., 3) to the nearest surface (room walls or a box); 0 inside a box."""
        p_w = np.asarray(p_w, dtype=np.float64)
        d_room = np.min(np.concatenate([p_w - self.lo[0], self.hi[0] - p_w], -1), -1)  # inside the room: > 0
        d_box = box_distance(p_w[..., None, :], self.lo[1:], self.hi[1:])  # (..., B-1)
        return np.minimum(d_room, d_box.min(-1) if d_box.shape[-1] else np.inf)

    def inside_box(self, p_w: np.ndarray) -> np.ndarray:
        """True for points (..., 3) inside a furniture box or outside the room."""
        p_w = np.asarray(p_w, dtype=np.float64)
        out_room = np.any((p_w <= self.lo[0]) | (p_w >= self.hi[0]), -1)
        inside = np.all((p_w[..., None, :] > self.lo[1:]) & (p_w[..., None, :] < self.hi[1:]), -1).any(-1)
        return out_room | inside


def box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Euclidean distance [m] from points ``p`` (..., 3) to solid boxes ``[lo, hi]`` (broadcast), 0 inside."""
    d = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    return np.linalg.norm(d, axis=-1)


# --------------------------------------------------------------------------- furniture
def along_wall(wall: int, s0: float, s1: float, depth: float, z0: float, z1: float, size, gap: float = 0.0):
    """Box against wall ``wall`` (0: y=0, 1: x=Lx, 2: y=Ly, 3: x=0) spanning [s0, s1] along it."""
    Lx, Ly, _ = size
    if wall == 0:
        return [s0, gap, z0], [s1, gap + depth, z1]
    if wall == 1:
        return [Lx - gap - depth, s0, z0], [Lx - gap, s1, z1]
    if wall == 2:
        return [s0, Ly - gap - depth, z0], [s1, Ly - gap, z1]
    return [gap, s0, z0], [gap + depth, s1, z1]


def _furniture(rng: np.random.Generator, size: np.ndarray, band: float, walls: list[int]):
    """Furniture boxes ``[(name, lo, hi, style)]``: in the wall band, low in the middle, at the ceiling."""
    Lx, Ly, Lz = size
    boxes: list[tuple[str, list[float], list[float], str]] = []
    for wall in walls:
        # walls y=0 / y=Ly leave the corners to the walls x=0 / x=Lx (no interpenetrating furniture)
        start, end = (band, Lx - band) if wall in (0, 2) else (0.0, Ly)
        length = Lx if wall in (0, 2) else Ly
        s = start + float(rng.uniform(0.05, 0.5))
        while True:
            kind = rng.choice(["cabinet", "table", "shelf", "stack", "gap"], p=[0.25, 0.2, 0.2, 0.25, 0.1])
            width = float(rng.uniform(0.5, 1.3))
            if s + width > end - 0.05:
                break
            depth = float(rng.uniform(0.35, band))
            if kind == "cabinet":
                lo, hi = along_wall(wall, s, s + width, depth, 0.0, float(rng.uniform(0.6, 2.1)), size)
                boxes.append(("cabinet", lo, hi, "object"))
            elif kind == "table":
                top = float(rng.uniform(0.68, 0.8))
                lo, hi = along_wall(wall, s, s + width, depth, top - 0.04, top, size)
                boxes.append(("table_top", lo, hi, "object"))
                leg = 0.05
                for ds in (0.02, width - 0.02 - leg):
                    for dd in (0.02, depth - 0.02 - leg):
                        lo, hi = along_wall(wall, s + ds, s + ds + leg, leg, 0.0, top - 0.04, size, gap=dd)
                        boxes.append(("table_leg", lo, hi, "object"))
                if rng.uniform() < 0.7:  # something on the table
                    w2 = float(rng.uniform(0.2, min(0.5, width - 0.1)))
                    s2 = s + float(rng.uniform(0.05, width - w2 - 0.05))
                    lo, hi = along_wall(
                        wall,
                        s2,
                        s2 + w2,
                        float(rng.uniform(0.15, depth - 0.05)),
                        top,
                        top + float(rng.uniform(0.1, 0.4)),
                        size,
                        gap=0.03,
                    )
                    boxes.append(("table_item", lo, hi, "object"))
            elif kind == "shelf":
                height = float(rng.uniform(1.0, 2.0))
                t = 0.025
                for ds in (0.0, width - t):
                    lo, hi = along_wall(wall, s + ds, s + ds + t, depth, 0.0, height, size)
                    boxes.append(("shelf_side", lo, hi, "object"))
                lo, hi = along_wall(wall, s, s + width, 0.01, 0.0, height, size)
                boxes.append(("shelf_back", lo, hi, "object"))
                n_boards = int(rng.integers(3, 6))
                for z in np.linspace(0.05, height - t, n_boards):
                    lo, hi = along_wall(wall, s + t, s + width - t, depth, float(z), float(z) + t, size)
                    boxes.append(("shelf_board", lo, hi, "object"))
                    if rng.uniform() < 0.6 and z + 0.1 < height - t:  # books / boxes on the board
                        w2 = float(rng.uniform(0.1, 0.4)) * (width - 2 * t)
                        s2 = s + t + float(rng.uniform(0, width - 2 * t - w2))
                        zt = min(float(z) + t + float(rng.uniform(0.08, 0.3)), height - t)
                        lo, hi = along_wall(
                            wall,
                            s2,
                            s2 + w2,
                            depth * float(rng.uniform(0.5, 0.95)),
                            float(z) + t,
                            zt,
                            size,
                            gap=0.01,
                        )
                        boxes.append(("shelf_item", lo, hi, "object"))
            elif kind == "stack":
                z = 0.0
                for _ in range(int(rng.integers(1, 4))):
                    bw = float(rng.uniform(0.25, min(width, 0.7)))
                    bd = float(rng.uniform(0.25, depth))
                    bh = float(rng.uniform(0.2, 0.5))
                    s2 = s + float(rng.uniform(0, width - bw))
                    lo, hi = along_wall(wall, s2, s2 + bw, bd, z, z + bh, size, gap=float(rng.uniform(0, depth - bd)))
                    boxes.append(("box", lo, hi, "object"))
                    z += bh
            s += width + float(rng.uniform(0.05, 0.6))
        # pictures / posters on the wall above the furniture band height
        for _ in range(int(rng.integers(1, 4))):
            pw = float(rng.uniform(0.3, 1.0))
            s0 = float(rng.uniform(0.1, max(0.2, length - pw - 0.1)))
            z0 = float(rng.uniform(1.2, max(1.3, Lz - 1.1)))
            lo, hi = along_wall(wall, s0, s0 + pw, 0.02, z0, z0 + float(rng.uniform(0.3, 0.8)), size)
            boxes.append(("picture", lo, hi, "object"))
    # low objects in the middle: a rug and maybe a low table (top below free_z[0] - clearance)
    rug_w, rug_d = float(rng.uniform(1.0, 2.0)), float(rng.uniform(1.0, 2.5))
    cx, cy = Lx / 2 + float(rng.uniform(-0.4, 0.4)), Ly / 2 + float(rng.uniform(-0.4, 0.4))
    boxes.append(("rug", [cx - rug_w / 2, cy - rug_d / 2, 0.0], [cx + rug_w / 2, cy + rug_d / 2, 0.012], "object"))
    if rng.uniform() < 0.6:
        h = float(rng.uniform(0.25, 0.4))
        tw, td = float(rng.uniform(0.4, 0.9)), float(rng.uniform(0.4, 0.9))
        boxes.append(("low_table", [cx - tw / 2, cy - td / 2, 0.0], [cx + tw / 2, cy + td / 2, h], "object"))
    # a ceiling lamp (thin slab under the ceiling)
    lw, ld = float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.3, 0.8))
    lx, ly = Lx / 2 + float(rng.uniform(-0.5, 0.5)), Ly / 2 + float(rng.uniform(-0.8, 0.8))
    boxes.append(("lamp", [lx - lw / 2, ly - ld / 2, Lz - 0.05], [lx + lw / 2, ly + ld / 2, Lz], "plain"))
    return boxes


def make_scene(
    seed: int,
    preset: str = "textured",
    rgb: bool = False,
    texel: float = 0.005,
    clearance: float = 0.5,
) -> Scene:
    """Build a random room.

    Args:
        seed: any non-negative int; the same seed gives the same scene (geometry, textures, shading).
        preset: ``textured`` or ``whitewall`` (the wall ``x = Lx`` is bare and textureless).
        rgb: keep RGB textures (NYU) instead of grey luminance (EuRoC).
        texel: texture resolution [m].
        clearance: distance [m] kept between the free region and every surface.

    Returns:
        The :class:`Scene`.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; expected one of {PRESETS}")
    if preset in ROOM_PRESETS:
        from sim.rooms import make_room

        return make_room(seed, preset, rgb=rgb)
    if clearance < 0:
        raise ValueError(f"clearance must be >= 0, got {clearance}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CE2E]))
    Lx = float(rng.uniform(3.8, 4.6))
    Ly = float(rng.uniform(4.7, 5.6))
    Lz = float(rng.uniform(2.7, 3.2))
    size = np.array([Lx, Ly, Lz])
    band = float(rng.uniform(0.6, 0.8))
    whitewall = preset == "whitewall"
    walls = [0, 2, 3] if whitewall else [0, 1, 2, 3]
    free_lo = np.array([band + clearance, band + clearance, 1.0])
    free_hi = np.array([Lx - band - clearance, Ly - band - clearance, min(Lz - 0.05 - clearance, 2.0)])
    if whitewall:  # no furniture in front of the bare wall: the camera may come closer to it
        free_hi[0] = Lx - 1.2
    furniture = _furniture(rng, size, band, walls)

    names = ["room"] + [f[0] for f in furniture]
    lo = np.array([[0.0, 0.0, 0.0]] + [f[1] for f in furniture], dtype=np.float64)
    hi = np.array([[Lx, Ly, Lz]] + [f[2] for f in furniture], dtype=np.float64)
    styles_box = ["room"] + [f[3] for f in furniture]

    # colours
    wall_base = rng.uniform(0.55, 0.9) * np.clip(1.0 + rng.uniform(-0.12, 0.12, 3), 0, 1.2)
    floor_base = rng.uniform(0.25, 0.6) * np.clip(1.0 + rng.uniform(-0.3, 0.3, 3), 0, 1.5)
    ceil_base = np.full(3, rng.uniform(0.75, 0.92))
    light = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 1.3])
    light /= np.linalg.norm(light)

    images, shade = [], []
    for b in range(len(names)):
        ext = hi[b] - lo[b]
        obj_base = rng.uniform(0.15, 0.85, 3)
        for axis in range(3):
            ua, va = FACE_UV_AXES[axis]
            for side in range(2):
                if b == 0:
                    normal = np.zeros(3)
                    normal[axis] = 1.0 if side == 0 else -1.0  # room faces look inwards
                    if axis == 2:
                        style, base = ("floor", floor_base) if side == 0 else ("ceiling", ceil_base)
                    elif whitewall and (axis, side) == WHITEWALL_FACE:
                        style, base = "plain", np.full(3, 0.8)
                    else:
                        style, base = "wall", wall_base
                else:
                    normal = np.zeros(3)
                    normal[axis] = -1.0 if side == 0 else 1.0
                    style = styles_box[b]
                    base = np.full(3, 0.95) if style == "plain" else obj_base
                images.append(make_texture(rng, ext[ua], ext[va], texel, style, base))
                shade.append(0.62 + 0.38 * max(0.0, float(normal @ light)))
    atlas = TextureAtlas.pack(images, texel, grey=not rgb)
    return Scene(
        size=size,
        lo=lo,
        hi=hi,
        names=names,
        free_lo=free_lo,
        free_hi=free_hi,
        clearance=clearance,
        atlas=atlas,
        shade=np.asarray(shade, np.float32),
        whitewall=whitewall,
        seed=int(seed),
        light_dir=light,
    )


def scene_from_boxes(
    size, lo=(), hi=(), albedo: float = 0.5, texel: float = 0.05, clearance: float = 0.0, rgb: bool = False
) -> Scene:
    """A room ``[0, size]`` with given furniture boxes and uniform textures (known-answer tests).

    Args:
        size: (3,) room extent [m].
        lo, hi: (B, 3) furniture box corners [m] (may be empty).
        albedo: uniform grey albedo of every face.
        texel: texture resolution [m].
        clearance: recorded clearance; the free region is the room shrunk by it.
        rgb: RGB atlas instead of grey.

    Returns:
        The :class:`Scene` (shade 1 on every face).
    """
    size = np.asarray(size, dtype=np.float64).reshape(3)
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    if lo.shape != hi.shape or np.any(hi <= lo) or np.any(size <= 0):
        raise ValueError(f"boxes need lo < hi (got lo {lo.tolist()}, hi {hi.tolist()}) and a positive room size")
    all_lo = np.concatenate([np.zeros((1, 3)), lo])
    all_hi = np.concatenate([size[None], hi])
    images = []
    for b in range(all_lo.shape[0]):
        ext = all_hi[b] - all_lo[b]
        for axis in range(3):
            ua, va = FACE_UV_AXES[axis]
            h = max(2, int(np.ceil(ext[va] / texel)) + 1)
            w = max(2, int(np.ceil(ext[ua] / texel)) + 1)
            images += [np.full((h, w, 3), albedo, np.float32)] * 2
    return Scene(
        size=size,
        lo=all_lo,
        hi=all_hi,
        names=["room"] + ["box"] * lo.shape[0],
        free_lo=np.full(3, clearance),
        free_hi=size - clearance,
        clearance=clearance,
        atlas=TextureAtlas.pack(images, texel, grey=not rgb),
        shade=np.ones(6 * all_lo.shape[0], np.float32),
    )
