"""Rooms that look like rooms: the scenes of the realistic presets ``flight``, ``handheld`` and ``tabletop``.

Compared with :func:`sim.scenes.make_scene` (flat shapes on paper, corners on every wall):

- natural textures (:mod:`sim.natural`): 1/f noise, wood, fabric, concrete, brushed metal; plain painted walls
  and floors carry almost no texture, clutter (shelves, boxes, machines, books) carries the corners;
- furniture-scale objects from 0.3 m (boxes, crates) to 8 m (racks, machines along a hall's walls);
- smooth shading: a point light under the ceiling lights every pixel by ``ambient + diffuse * cos / (1 + (d /
  range)^2)``, so surface orientation and distance show in the image; windows and lamps glow (emissive faces,
  brighter than anything lit), which makes auto-exposure work.

``flight``: a machine hall (8-11 m x 10-13 m x 4-5.5 m) with racks, machines, pillars and crates along the
walls, a free middle where a MAV takes off from the floor. ``handheld``: an office / living room (4-6 m) with a
mix of bare painted walls and cluttered furniture. ``tabletop``: a table with 6-12 objects of 5-30 cm in a small
room; the camera stays 0.2-1.5 m from them.
"""

from __future__ import annotations

import numpy as np

from sim.natural import make_natural_texture
from sim.scenes import FACE_UV_AXES, ROOM_PRESETS, Scene, along_wall
from sim.textures import TextureAtlas

__all__ = ["ROOM_PRESETS", "make_room", "face_normals"]


def face_normals(n_boxes: int) -> np.ndarray:
    """(6B, 3) float32 normals of every face, pointing into the free space (room faces look inwards)."""
    f = np.arange(6 * n_boxes)
    axis, side, box = (f % 6) // 2, f % 2, f // 6
    sign = np.where(box == 0, np.where(side == 0, 1.0, -1.0), np.where(side == 0, -1.0, 1.0))
    n = np.zeros((f.size, 3), np.float32)
    n[f, axis] = sign
    return n


def _box(name, lo, hi, style):
    return (name, [float(x) for x in lo], [float(x) for x in hi], style)


def _along_walls(rng, size, band, walls, kinds, probs, wmin, wmax, hmax):
    """Objects standing in the band along each wall: (name, lo, hi, style)."""
    Lx, Ly, Lz = size
    out = []
    for wall in walls:
        start, end = (band, Lx - band) if wall in (0, 2) else (0.0, Ly)
        s = start + float(rng.uniform(0.1, 0.8))
        while True:
            kind = str(rng.choice(kinds, p=probs))
            width = float(rng.uniform(wmin, wmax))
            if s + width > end - 0.1:
                break
            depth = float(rng.uniform(0.35, band))
            if kind == "rack":  # open shelving: uprights, boards, boxes on the boards
                height = float(rng.uniform(1.5, hmax))
                t = 0.05
                for ds in (0.0, width - t):
                    post = along_wall(wall, s + ds, s + ds + t, depth, 0, height, size)
                    out.append(_box("rack_post", *post, "metal"))
                for z in np.linspace(0.1, height - t, int(rng.integers(3, 6))):
                    lo, hi = along_wall(wall, s + t, s + width - t, depth, float(z), float(z) + t, size)
                    out.append(_box("rack_board", lo, hi, "wood"))
                    if z + 0.3 < height:
                        x = s + t
                        while x < s + width - t - 0.3:
                            bw = float(rng.uniform(0.2, 0.6))
                            if rng.uniform() < 0.7 and x + bw < s + width - t:
                                bh = float(rng.uniform(0.15, 0.5))
                                lo, hi = along_wall(
                                    wall,
                                    x,
                                    x + bw,
                                    depth * float(rng.uniform(0.5, 0.95)),
                                    float(z) + t,
                                    min(float(z) + t + bh, height - t),
                                    size,
                                    gap=0.02,
                                )
                                out.append(_box("rack_item", lo, hi, "clutter"))
                            x += bw + float(rng.uniform(0.02, 0.2))
            elif kind == "machine":  # a big block with panels
                lo, hi = along_wall(wall, s, s + width, depth, 0.0, float(rng.uniform(0.8, hmax)), size)
                out.append(_box("machine", lo, hi, str(rng.choice(["metal", "clutter"]))))
            elif kind == "cabinet":
                lo, hi = along_wall(wall, s, s + width, depth, 0.0, float(rng.uniform(0.7, 2.0)), size)
                out.append(_box("cabinet", lo, hi, str(rng.choice(["wood", "clutter", "metal"]))))
            elif kind == "crates":
                z = 0.0
                for _ in range(int(rng.integers(1, 4))):
                    bw = float(rng.uniform(0.3, min(width, 0.9)))
                    bd = float(rng.uniform(0.3, depth))
                    bh = float(rng.uniform(0.3, 0.7))
                    s2 = s + float(rng.uniform(0, width - bw))
                    lo, hi = along_wall(wall, s2, s2 + bw, bd, z, z + bh, size, gap=float(rng.uniform(0, depth - bd)))
                    out.append(_box("crate", lo, hi, str(rng.choice(["wood", "clutter"]))))
                    z += bh
            elif kind == "sofa":
                lo, hi = along_wall(wall, s, s + width, depth, 0.0, 0.45, size)
                out.append(_box("sofa_seat", lo, hi, "fabric"))
                lo, hi = along_wall(wall, s, s + width, 0.2, 0.45, 0.85, size)
                out.append(_box("sofa_back", lo, hi, "fabric"))
            elif kind == "desk":
                top = float(rng.uniform(0.7, 0.78))
                lo, hi = along_wall(wall, s, s + width, depth, top - 0.03, top, size)
                out.append(_box("desk_top", lo, hi, "wood"))
                for ds in (0.02, width - 0.07):
                    lo, hi = along_wall(wall, s + ds, s + ds + 0.05, depth - 0.04, 0.0, top - 0.03, size, gap=0.02)
                    out.append(_box("desk_side", lo, hi, "wood"))
                for _ in range(int(rng.integers(1, 4))):  # things on the desk
                    bw = float(rng.uniform(0.1, 0.4))
                    s2 = s + float(rng.uniform(0.05, max(0.06, width - bw - 0.05)))
                    lo, hi = along_wall(
                        wall,
                        s2,
                        s2 + bw,
                        float(rng.uniform(0.1, depth - 0.05)),
                        top,
                        top + float(rng.uniform(0.05, 0.35)),
                        size,
                        gap=float(rng.uniform(0.02, 0.1)),
                    )
                    out.append(_box("desk_item", lo, hi, "clutter"))
            s += width + float(rng.uniform(0.1, 1.0))
    return out


def _wall_items(rng, size, walls, n_range, z_lo, windows: int):
    """Pictures, boards and windows on the walls: (name, lo, hi, style)."""
    Lx, Ly, Lz = size
    out = []
    for wall in walls:
        length = Lx if wall in (0, 2) else Ly
        for _ in range(int(rng.integers(*n_range))):
            pw = float(rng.uniform(0.4, 1.4))
            s0 = float(rng.uniform(0.2, max(0.3, length - pw - 0.2)))
            z0 = float(rng.uniform(z_lo, max(z_lo + 0.1, Lz - 1.2)))
            lo, hi = along_wall(wall, s0, s0 + pw, 0.02, z0, z0 + float(rng.uniform(0.3, 0.9)), size)
            out.append(_box("picture", lo, hi, "clutter"))
    for _ in range(windows):
        wall = int(rng.choice(walls))
        length = Lx if wall in (0, 2) else Ly
        pw = float(rng.uniform(0.8, 2.0))
        s0 = float(rng.uniform(0.3, max(0.4, length - pw - 0.3)))
        z0 = float(rng.uniform(1.0, max(1.1, Lz - 2.0)))
        lo, hi = along_wall(wall, s0, s0 + pw, 0.01, z0, z0 + float(rng.uniform(0.8, 1.4)), size)
        out.append(_box("window", lo, hi, "window"))
    return out


def make_room(seed: int, preset: str, rgb: bool = False, texel: float | None = None) -> Scene:
    """Build a realistic room for ``preset`` (one of :data:`ROOM_PRESETS`).

    Args:
        seed: same seed, same scene.
        preset: ``flight`` (a hall), ``handheld`` (a room) or ``tabletop`` (a table with small objects).
        rgb: keep RGB textures (NYU) instead of grey luminance (EuRoC).
        texel: texture resolution [m]; default 8 mm (flight), 5 mm (handheld), 2 mm (tabletop).

    Returns:
        The :class:`~sim.scenes.Scene`, with ``point_light`` and ``emissive`` set (per-pixel shading).
    """
    if preset not in ROOM_PRESETS:
        raise ValueError(f"unknown room preset {preset!r}; expected one of {ROOM_PRESETS}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x200, ROOM_PRESETS.index(preset)]))
    if preset == "flight":
        size = np.array([rng.uniform(8.0, 11.0), rng.uniform(10.0, 13.0), rng.uniform(4.0, 5.5)])
        band = float(rng.uniform(1.2, 1.8))
        clearance = 0.8
        furniture = _along_walls(
            rng,
            size,
            band,
            [0, 1, 2, 3],
            ["rack", "machine", "crates", "cabinet"],
            [0.35, 0.25, 0.3, 0.1],
            0.8,
            3.0,
            min(3.5, size[2] - 0.5),
        )
        furniture += _wall_items(rng, size, [0, 1, 2, 3], (0, 3), 2.5, windows=int(rng.integers(1, 3)))
        for _ in range(int(rng.integers(6, 12))):  # pipes along the walls (horizontal) and up them (vertical)
            wall = int(rng.integers(0, 4))
            length = size[0] if wall in (0, 2) else size[1]
            th = float(rng.uniform(0.08, 0.35))
            gap = float(rng.uniform(0.05, band - th))
            if rng.uniform() < 0.6:
                z = float(rng.uniform(1.8, size[2] - 0.5))
                s0 = float(rng.uniform(0.0, length * 0.5))
                lo, hi = along_wall(
                    wall, s0, min(length, s0 + float(rng.uniform(2.0, length))), th, z, z + th, size, gap=gap
                )
            else:
                s0 = float(rng.uniform(0.2, length - 0.5))
                lo, hi = along_wall(wall, s0, s0 + th, th, 0.0, float(rng.uniform(2.0, size[2])), size, gap=gap)
            furniture.append(_box("pipe", lo, hi, "metal"))
        for _ in range(int(rng.integers(4, 9))):  # ceiling light strips
            x = float(rng.uniform(1.0, size[0] - 2.0))
            y = float(rng.uniform(1.0, size[1] - 1.0))
            furniture.append(
                _box(
                    "lamp",
                    [x, y, size[2] - 0.06],
                    [x + float(rng.uniform(0.8, 1.6)), y + 0.12, size[2] - 0.01],
                    "window",
                )
            )
        for _ in range(int(rng.integers(2, 5))):  # pillars
            x = float(rng.choice([band + 0.3, size[0] - band - 0.7]))
            y = float(rng.uniform(band, size[1] - band - 0.4))
            furniture.append(_box("pillar", [x, y, 0.0], [x + 0.4, y + 0.4, size[2]], "concrete"))
        free_lo = np.array([band + 0.7 + clearance, band + clearance, 0.9])
        free_hi = np.array([size[0] - band - 0.7 - clearance, size[1] - band - clearance, min(2.6, size[2] - 1.5)])
        styles = {"wall": "concrete", "floor": "concrete", "ceiling": "metal", "plain_walls": 1}
        tex = texel or 0.008
        light = np.array([size[0] / 2, size[1] / 2, size[2] - 0.3])
        light_range = 6.0
    elif preset == "handheld":
        size = np.array([rng.uniform(4.0, 5.0), rng.uniform(4.8, 6.0), rng.uniform(2.6, 3.1)])
        band = float(rng.uniform(0.6, 0.8))
        clearance = 0.5
        furniture = _along_walls(
            rng,
            size,
            band,
            [0, 1, 2, 3],
            ["rack", "cabinet", "sofa", "desk", "crates"],
            [0.2, 0.2, 0.2, 0.25, 0.15],
            0.5,
            1.6,
            2.2,
        )
        furniture += _wall_items(rng, size, [0, 1, 2, 3], (0, 2), 1.3, windows=1)
        free_lo = np.array([band + clearance, band + clearance, 1.0])
        free_hi = np.array([size[0] - band - clearance, size[1] - band - clearance, min(size[2] - 0.6, 1.9)])
        styles = {"wall": "paint", "floor": "wood", "ceiling": "paint", "plain_walls": 1}
        tex = texel or 0.005
        light = np.array([size[0] / 2, size[1] / 2, size[2] - 0.2])
        light_range = 3.5
    else:  # tabletop
        size = np.array([rng.uniform(3.0, 3.6), rng.uniform(3.0, 3.6), rng.uniform(2.5, 2.8)])
        clearance = 0.15
        furniture = _along_walls(
            rng, size, 0.5, [0, 1, 2, 3], ["cabinet", "rack", "desk"], [0.4, 0.3, 0.3], 0.5, 1.2, 2.0
        )
        furniture += _wall_items(rng, size, [0, 1, 2, 3], (0, 2), 1.2, windows=1)
        cx, cy = size[0] / 2, size[1] / 2
        tw, td, top = float(rng.uniform(1.0, 1.4)), float(rng.uniform(0.7, 0.9)), float(rng.uniform(0.72, 0.78))
        furniture.append(
            _box("table_top", [cx - tw / 2, cy - td / 2, top - 0.04], [cx + tw / 2, cy + td / 2, top], "clutter")
        )
        for sx in (-1, 1):
            for sy in (-1, 1):
                x, y = cx + sx * (tw / 2 - 0.06), cy + sy * (td / 2 - 0.06)
                furniture.append(
                    _box("table_leg", [x - 0.025, y - 0.025, 0.0], [x + 0.025, y + 0.025, top - 0.04], "wood")
                )
        placed = []
        for _ in range(int(rng.integers(6, 13))):
            for _try in range(20):
                ow, od = float(rng.uniform(0.05, 0.3)), float(rng.uniform(0.05, 0.25))
                oh = float(rng.uniform(0.03, 0.3))
                x = float(rng.uniform(cx - tw / 2 + 0.03, cx + tw / 2 - 0.03 - ow))
                y = float(rng.uniform(cy - td / 2 + 0.03, cy + td / 2 - 0.03 - od))
                if all(x + ow < a or x > c or y + od < b or y > d for a, b, c, d in placed):
                    placed.append((x, y, x + ow, y + od))
                    furniture.append(
                        _box(
                            "object",
                            [x, y, top],
                            [x + ow, y + od, top + oh],
                            str(rng.choice(["clutter", "wood", "fabric", "metal", "clutter"])),
                        )
                    )
                    break
        free_lo = np.array([cx - tw / 2 - 0.5, cy - td / 2 - 0.5, top + 0.35])
        free_hi = np.array([cx + tw / 2 + 0.5, cy + td / 2 + 0.5, top + 0.9])
        styles = {"wall": "paint", "floor": "wood", "ceiling": "paint", "plain_walls": 1}
        tex = texel or 0.003
        light = np.array([cx + float(rng.uniform(-0.5, 0.5)), cy + float(rng.uniform(-0.5, 0.5)), size[2] - 0.3])
        light_range = 2.5

    names = ["room"] + [f[0] for f in furniture]
    lo = np.array([[0.0, 0.0, 0.0]] + [f[1] for f in furniture], dtype=np.float64)
    hi = np.array([list(size)] + [f[2] for f in furniture], dtype=np.float64)
    box_style = ["room"] + [f[3] for f in furniture]
    plain = set(rng.choice(4, size=styles["plain_walls"], replace=False).tolist())  # bare walls
    wall_base = rng.uniform(0.5, 0.85) * np.clip(1.0 + rng.uniform(-0.1, 0.1, 3), 0, 1.2)
    floor_base = rng.uniform(0.25, 0.55) * np.clip(1.0 + rng.uniform(-0.25, 0.25, 3), 0, 1.5)
    ceil_base = np.full(3, rng.uniform(0.7, 0.9))
    images, shade, emissive = [], [], []
    wall_ids = {(1, 0): 0, (0, 1): 1, (1, 1): 2, (0, 0): 3}  # (axis, side) -> wall number of _wall_box
    for b in range(len(names)):
        ext = hi[b] - lo[b]
        obj_base = rng.uniform(0.04, 0.9) * np.clip(1.0 + rng.uniform(-0.2, 0.2, 3), 0.0, 1.5)
        for axis in range(3):
            ua, va = FACE_UV_AXES[axis]
            for side in range(2):
                glow = False
                clutter = 1.0
                if b == 0:
                    if axis == 2:
                        style, base = (styles["floor"], floor_base) if side == 0 else (styles["ceiling"], ceil_base)
                    else:
                        style, base = styles["wall"], wall_base
                        if wall_ids[(axis, side)] in plain:
                            style = "paint"
                        elif style == "paint":
                            style, clutter = "clutter", 0.8  # a wall with posters, notes, switches
                elif box_style[b] == "window":
                    style, base, glow = "window", np.full(3, 0.95), True
                else:
                    style, base = box_style[b], obj_base
                images.append(make_natural_texture(rng, ext[ua], ext[va], tex, style, base, clutter))
                shade.append(4.0 if glow else 1.0)
                emissive.append(glow)
    return Scene(
        size=size,
        lo=lo,
        hi=hi,
        names=names,
        free_lo=free_lo,
        free_hi=free_hi,
        clearance=clearance,
        atlas=TextureAtlas.pack(images, tex, grey=not rgb),
        shade=np.asarray(shade, np.float32),
        whitewall=False,
        seed=int(seed),
        point_light=light,
        light_range=float(light_range),
        emissive=np.asarray(emissive, bool),
        preset=preset,
    )
