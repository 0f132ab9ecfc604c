"""Offscreen rendering of sphere packings with Taichi kernels (headless, CPU or GPU backend).

Algorithm (one frame):
1. Grid build (kernels). The spheres' bounding box is cut into a uniform grid of cubic cells
   (edge ~ the cube root of the box volume per sphere). Each sphere is inserted into every cell
   its bounding box overlaps: count (parallel, integer atomics), exclusive scan (serial), scatter
   (serial, so each cell lists its spheres in ascending index order and the frame is
   deterministic).
2. Ray casting (one kernel, one thread per pixel). The camera ray is clipped to the kept side
   of the optional cutting plane, then marches the grid cells front to back (3D DDA,
   Amanatides-Woo) testing the spheres listed in each cell. The nearest hit is final as soon as
   it lies before the exit of the current cell, because any sphere hit at parameter t is listed
   in the cell that contains the point at t. A sphere whose entry point is clipped by the plane
   is hit on the plane: that is its cut face (flat disk, darker, with a dark rim).
3. Shading: Lambert from a camera-attached key light plus ambient light attenuated by analytic
   sphere ambient occlusion (each neighbour sphere of radius r at distance l occludes a point
   with normal n by max(n.d, 0) (r / l)^2, summed over the spheres of the grid cells within an
   AO radius of the point; each sphere counted once, in the first cell common to its box and the
   query box). Deterministic, no noise. Cut faces are flat and unlit (the sphere's colour,
   CUT_FACE_SHADE = 1, with a darker rim), so a section's cut faces show the colour bar's
   colours exactly; spheres seen whole are lit (up to 1.14 times their colour, clipped).
4. Walls are composited over the result in the same kernel: plane plates (disks) and finite
   cylinders drawn translucent, with the disk rims, cylinder rims and (via a grazing-angle
   term) the cylinder silhouettes drawn as dark outlines. Walls on the removed side of the
   cutting plane are removed too.
5. Colour bar, legend, scale bar and time label are composited afterwards with matplotlib
   (Agg, no display); the 3D image itself only comes from the kernels above.

Invariants: image row 0 is the top of the picture; the cutting plane (point p0, unit normal n)
keeps the half-space (x - p0).n >= 0 (n points into the kept half); the camera presets look
from the removed side. Device buffers are allocated with capacities (spheres, cells, grid
items, image pixels) and grown, never truncated; a frame that fits reuses them, so repeated
frames neither reallocate nor recompile. Units are SI (m, m/s) inside; labels use mm and mm/s.
"""

import argparse
import contextlib
import dataclasses
import functools
import importlib.util
import math
import os
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import taichi as ti

from . import backend, io
from .state import field_record
from .contacts import exclusive_scan

PLANE, CYLINDER = 0, 1
MAX_WALLS = 16
COLOR_MODES = ("layer", "speed", "vx", "bond-damage")
CAMERA_PRESETS = ("iso", "front", "perspective")
ANIMATION_EXTENSIONS = (".gif", ".mp4")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def check_output(out, frame: int = -1) -> None:
    """ValueError unless `out` can be an image or animation file: a known extension (the
    format is chosen from it) and not an existing directory; and unless a `frame` other than
    the default (the last) goes with an image. Called before any rendering."""
    out = Path(out)
    suffix = out.suffix.lower()
    if frame != -1 and suffix in ANIMATION_EXTENSIONS:
        raise ValueError(f"--frame {frame} picks the frame of an image; an animation ({out}) "
                         "takes --frames K,K,... (default all)")
    if suffix not in IMAGE_EXTENSIONS + ANIMATION_EXTENSIONS:
        raise ValueError(f"--out {out}: the extension sets the format; expected one of "
                         f"{', '.join(IMAGE_EXTENSIONS)} (an image) or "
                         f"{', '.join(ANIMATION_EXTENSIONS)} (an animation)")
    if out.is_dir():
        raise ValueError(f"--out {out}: is a directory, expected an image file name")

#: course colours: binder course (dark grey-brown), surface course (light grey-beige). A
#: grain's layer id is its course's position in the prepare stage's `courses`, read from the
#: states file's scenario (the default ("binder", "surface") when the file has none).
LAYER_COLORS = np.array([[0.36, 0.29, 0.23], [0.80, 0.76, 0.68]])
COURSE_COLOR = {"binder": 0, "surface": 1}
DEFAULT_COURSES = ("binder", "surface")
NO_BOND_COLOR = (0.72, 0.72, 0.72)
COLORMAPS = {"speed": "viridis", "vx": "coolwarm", "bond-damage": "plasma"}

# shading constants (compile-time constants of the kernels)
AMBIENT = 0.42
DIFFUSE = 0.72
AO_STRENGTH = 0.9
AO_RADIUS_FACTOR = 1.0          # AO radius = factor * radius of the sphere hit (capped to a cell)
CUT_FACE_SHADE = 1.0            # colour factor of cut faces (flat, unlit): their colour is
                                # the colour bar's (0.88 before session 44 misread values 12 %)
CUT_RIM_SHADE = 0.45            # albedo factor of the rim of cut faces
CUT_RIM_PIXELS = 1.2
WALL_COLOR = (0.30, 0.42, 0.60)
WALL_LINE_COLOR = (0.12, 0.16, 0.24)
WALL_FILL_ALPHA = 0.07
WALL_GRAZING_ALPHA = 0.75       # extra opacity at grazing incidence: draws cylinder silhouettes
WALL_LINE_ALPHA = 0.85
WALL_LINE_PIXELS = 1.5
FAR = 1e30
COLORBAR_STRIP = 0.15           # fraction of the image width kept for the colour bar

Vec = Tuple[float, float, float]


# ----------------------------------------------------------------------------------------------
# cameras, sections, walls (NumPy side)

@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole or orthographic camera.

    kind: "ortho" or "perspective". eye, target (m): position and look-at point; up: a vector
    that ends up vertical in the image. fov_deg: vertical field of view of the perspective
    camera. ortho_width (m): horizontal extent of the orthographic view (the vertical extent
    follows from the image aspect ratio).
    """
    kind: str = "perspective"
    eye: Vec = (0.0, -0.5, 0.3)
    target: Vec = (0.0, 0.0, 0.06)
    up: Vec = (0.0, 0.0, 1.0)
    fov_deg: float = 30.0
    ortho_width: float = 0.2

    def __post_init__(self):
        if self.kind not in ("ortho", "perspective"):
            raise ValueError(f"camera kind {self.kind!r}: expected 'ortho' or 'perspective'")
        if not 0.0 < self.fov_deg < 179.0:
            raise ValueError(f"camera fov_deg {self.fov_deg} outside (0, 179)")
        if self.ortho_width <= 0.0:
            raise ValueError(f"camera ortho_width {self.ortho_width} must be > 0")
        forward = np.subtract(self.target, self.eye)
        if np.linalg.norm(forward) == 0.0:
            raise ValueError("camera eye and target coincide")
        if np.linalg.norm(np.cross(forward, self.up)) < 1e-9 * np.linalg.norm(forward):
            raise ValueError("camera up is parallel to the viewing direction")

    def basis(self):
        """(forward, right, up) unit vectors; right = forward x up."""
        f = np.asarray(self.target, float) - np.asarray(self.eye, float)
        f /= np.linalg.norm(f)
        r = np.cross(f, np.asarray(self.up, float))
        r /= np.linalg.norm(r)
        return f, r, np.cross(r, f)

    def half_extents(self, width: int, height: int):
        """Half extents of the image plane: metres (ortho) or tangents of half angles."""
        if self.kind == "ortho":
            half_w = 0.5 * self.ortho_width
        else:
            half_w = math.tan(math.radians(0.5 * self.fov_deg)) * width / height
        return half_w, half_w * height / width

    def pixel_size(self, width: int, height: int) -> float:
        """Metres per pixel: exact for ortho, at the target distance for perspective."""
        half_w, _ = self.half_extents(width, height)
        size = 2.0 * half_w / width
        if self.kind == "perspective":
            size *= float(np.linalg.norm(np.subtract(self.target, self.eye)))
        return size

    def project(self, points, width: int, height: int):
        """Pixel coordinates (column, row) of points (N,3), matching the renderer (pixel (i, j)
        has its centre at column j + 0.5, row i + 0.5); also returns the depth along forward."""
        f, r, u = self.basis()
        rel = np.asarray(points, float).reshape(-1, 3) - np.asarray(self.eye, float)
        depth = rel @ f
        half_w, half_h = self.half_extents(width, height)
        a, b = rel @ r, rel @ u
        if self.kind == "perspective":
            a, b = a / depth, b / depth
        col = (a / half_w + 1.0) * 0.5 * width
        row = (1.0 - b / half_h) * 0.5 * height
        return np.stack([col, row], axis=1), depth


def _unit(v):
    v = np.asarray(v, float)
    n = float(np.linalg.norm(v))
    if n == 0.0:
        raise ValueError("zero-length direction")
    return v / n


def _view_frame(view_normal=None):
    """Horizontal 'front' viewing direction and the image up vector for the presets."""
    z = np.array([0.0, 0.0, 1.0])
    if view_normal is None:
        return np.array([0.0, 1.0, 0.0]), z
    n = _unit(view_normal)
    horizontal = n - n[2] * z
    if np.linalg.norm(horizontal) < 1e-6:          # horizontal cut: look along it, y up
        return n, np.array([0.0, 1.0, 0.0])
    return _unit(horizontal), z


def camera_preset(name: str, lo, hi, *, width: int = 1600, height: int = 1200,
                  view_normal=None, spheres=None) -> Camera:
    """Camera framing the box [lo, hi] (m): "iso" (orthographic 3/4 view from above), "front"
    (orthographic, horizontal) or "perspective" (3/4 view). With a cutting plane, pass its normal
    as `view_normal`: the camera then looks along it, from the removed side. `spheres`
    (centres (N,3), radii (N,)) inside the box, when given, frame the view more tightly than the
    box corners (a cylinder's silhouette is narrower than its box's)."""
    if name not in CAMERA_PRESETS:
        raise ValueError(f"unknown camera preset {name!r}: expected one of {CAMERA_PRESETS}")
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    front, up = _view_frame(view_normal)
    if name == "front":
        forward = front
    else:
        side = np.cross(up, front)
        forward = _unit(front + 0.62 * side - 0.55 * up)
    if spheres is not None and len(spheres[0]):
        points, pad = np.asarray(spheres[0], float), np.asarray(spheres[1], float)
    else:
        points = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                           for z in (lo[2], hi[2])])
        pad = np.zeros(len(points))
    if name == "perspective":
        # nearest eye distance that keeps every sphere within 92 % of the half-extents
        fov = 32.0
        cam = Camera("perspective", tuple(centre - forward), tuple(centre), tuple(up), fov_deg=fov)
        _, r, u = cam.basis()
        tan_w, tan_h = cam.half_extents(width, height)
        rel = points - centre
        near = rel @ forward - pad
        dist = max(np.max((np.abs(rel @ r) + pad) / (0.92 * tan_w) - near),
                   np.max((np.abs(rel @ u) + pad) / (0.92 * tan_h) - near),
                   1.05 * np.max(-near) + 1e-6)
        return dataclasses.replace(cam, eye=tuple(centre - forward * dist))
    cam = Camera("ortho", tuple(centre - forward), tuple(centre), tuple(up), ortho_width=1.0)
    _, r, u = cam.basis()
    a, b = points @ r, points @ u
    a_lo, a_hi, b_lo, b_hi = np.min(a - pad), np.max(a + pad), np.min(b - pad), np.max(b + pad)
    # centre the image on the projected extent, eye well outside the box
    target = centre + (0.5 * (a_lo + a_hi) - centre @ r) * r + (0.5 * (b_lo + b_hi) - centre @ u) * u
    ortho_width = 1.08 * max(a_hi - a_lo, (b_hi - b_lo) * width / height, 1e-6)
    return Camera("ortho", tuple(target - forward * radius * 3.0), tuple(target), tuple(up),
                  ortho_width=float(ortho_width))


@dataclasses.dataclass(frozen=True)
class WallSet:
    """Walls to draw. kind (W,) 0 plane / 1 cylinder; point (W,3) m; direction (W,3) (plane:
    unit normal, cylinder: unit axis); radius (W,) m (cylinder radius; plate disk radius, <= 0
    for an unbounded plane); extent (W,2) m (cylinder axial range relative to point)."""
    kind: np.ndarray
    point: np.ndarray
    direction: np.ndarray
    radius: np.ndarray
    extent: np.ndarray

    @staticmethod
    def from_frame(frame: dict) -> "WallSet":
        w = len(frame.get("wall_kind", ()))
        return WallSet(
            kind=np.asarray(frame.get("wall_kind", np.zeros(0)), np.int32).reshape(w),
            point=np.asarray(frame.get("wall_point", np.zeros((0, 3))), float).reshape(w, 3),
            direction=np.asarray(frame.get("wall_direction", np.zeros((0, 3))), float).reshape(w, 3),
            radius=np.asarray(frame.get("wall_radius", np.zeros(0)), float).reshape(w),
            extent=np.asarray(frame.get("wall_extent", np.zeros((0, 2))), float).reshape(w, 2))

    def __len__(self):
        return len(self.kind)


def _as_walls(walls) -> Optional[WallSet]:
    if walls is None or isinstance(walls, WallSet):
        return walls
    if isinstance(walls, dict):
        if "wall_kind" in walls:
            return WallSet.from_frame(walls)
        return WallSet.from_frame({f"wall_{k}": v for k, v in walls.items()})
    raise TypeError(f"walls must be a WallSet, a dict of wall arrays or None, got {type(walls)}")


def resolve_section(section, x=None, walls: Optional[WallSet] = None):
    """Cutting plane as (point, unit normal) or None.

    "xz": the plane through the cylinder axis with normal +y (removes y < axis y); "yz": normal
    +x. The axis is the first cylinder wall's, else the centre of the particles' box.
    A (point, normal) pair is used as given; the normal points into the kept half-space.
    """
    if section is None:
        return None
    if isinstance(section, str):
        normals = {"xz": (0.0, 1.0, 0.0), "yz": (1.0, 0.0, 0.0)}
        if section not in normals:
            raise ValueError(f"unknown section {section!r}: expected 'xz', 'yz' or (point, normal)")
        point = np.zeros(3)
        cyl = None if walls is None else np.flatnonzero(walls.kind == CYLINDER)
        if cyl is not None and len(cyl):
            point = walls.point[cyl[0]].astype(float)
        elif x is not None and len(x):
            point = 0.5 * (np.min(x, axis=0) + np.max(x, axis=0))
        return point, np.asarray(normals[section])
    point, normal = section
    return np.asarray(point, float).reshape(3), _unit(normal).reshape(3)


# ----------------------------------------------------------------------------------------------
# device buffers and kernels

@field_record
class RenderBuffers:
    """Device buffers of the renderer, allocated once with capacities.

    Spheres (capacity `sphere_capacity`): center (m), radius (m), color (RGB in [0, 1]).
    Grid: cell_count, cell_start (CSR over `cell_capacity` cells), cell_items (sphere indices,
    capacity `item_capacity`). image: RGB uint8 (height_capacity, width_capacity).
    Walls (MAX_WALLS): kind, point, direction, radius, lo, hi.
    Per-frame parameters are 0-d fields so that changing them never recompiles a kernel.
    """

    def __init__(self, sphere_capacity: int, cell_capacity: int, item_capacity: int,
                 height_capacity: int, width_capacity: int):
        real = backend.real()
        self.sphere_capacity, self.cell_capacity = sphere_capacity, cell_capacity
        self.item_capacity = item_capacity
        self.height_capacity, self.width_capacity = height_capacity, width_capacity
        self.center = ti.Vector.field(3, real, shape=sphere_capacity)
        self.radius = ti.field(real, shape=sphere_capacity)
        self.color = ti.Vector.field(3, real, shape=sphere_capacity)
        self.cell_count = ti.field(ti.i32, shape=cell_capacity)
        self.cell_start = ti.field(ti.i32, shape=cell_capacity + 1)
        self.cell_items = ti.field(ti.i32, shape=item_capacity)
        self.image = ti.Vector.field(3, ti.u8, shape=(height_capacity, width_capacity))
        self.wall_kind = ti.field(ti.i32, shape=MAX_WALLS)
        self.wall_point = ti.Vector.field(3, real, shape=MAX_WALLS)
        self.wall_direction = ti.Vector.field(3, real, shape=MAX_WALLS)
        self.wall_radius = ti.field(real, shape=MAX_WALLS)
        self.wall_lo = ti.field(real, shape=MAX_WALLS)
        self.wall_hi = ti.field(real, shape=MAX_WALLS)
        # per-frame parameters
        self.sphere_count = ti.field(ti.i32, shape=())
        self.wall_count = ti.field(ti.i32, shape=())
        self.grid_origin = ti.Vector.field(3, real, shape=())
        self.grid_cell = ti.field(real, shape=())
        self.grid_pad = ti.field(real, shape=())
        self.grid_dims = ti.Vector.field(3, ti.i32, shape=())
        self.image_size = ti.Vector.field(2, ti.i32, shape=())          # (height, width)
        self.cam_eye = ti.Vector.field(3, real, shape=())
        self.cam_forward = ti.Vector.field(3, real, shape=())
        self.cam_right = ti.Vector.field(3, real, shape=())
        self.cam_up = ti.Vector.field(3, real, shape=())
        self.cam_ortho = ti.field(ti.i32, shape=())
        self.cam_half = ti.Vector.field(2, real, shape=())               # (half_w, half_h)
        self.cam_pixel = ti.field(real, shape=())    # m per pixel (ortho) or rad per pixel
        self.light_dir = ti.Vector.field(3, real, shape=())
        self.background = ti.Vector.field(3, real, shape=())
        self.section_on = ti.field(ti.i32, shape=())
        self.section_point = ti.Vector.field(3, real, shape=())
        self.section_normal = ti.Vector.field(3, real, shape=())

    def fits(self, spheres, cells, items, height, width) -> bool:
        return (spheres <= self.sphere_capacity and cells <= self.cell_capacity
                and items <= self.item_capacity and height <= self.height_capacity
                and width <= self.width_capacity)


@ti.func
def _cell_of(b: ti.template(), p):
    origin, inv, dims = b.grid_origin[None], 1.0 / b.grid_cell[None], b.grid_dims[None]
    c = ti.Vector([0, 0, 0])
    for a in ti.static(range(3)):
        k = ti.cast(ti.floor((p[a] - origin[a]) * inv), ti.i32)
        c[a] = ti.min(ti.max(k, 0), dims[a] - 1)
    return c


@ti.func
def _cell_index(b: ti.template(), c):
    dims = b.grid_dims[None]
    return (c[0] * dims[1] + c[1]) * dims[2] + c[2]


@ti.func
def _sphere_cells(b: ti.template(), i):
    e = b.radius[i] + b.grid_pad[None]
    return _cell_of(b, b.center[i] - e), _cell_of(b, b.center[i] + e)


@ti.kernel
def _grid_count(b: ti.template()):
    dims = b.grid_dims[None]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range(dims[0] * dims[1] * dims[2]):
        b.cell_count[c] = 0
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(b.sphere_count[None]):
        lo, hi = _sphere_cells(b, i)
        for cx in range(lo[0], hi[0] + 1):
            for cy in range(lo[1], hi[1] + 1):
                for cz in range(lo[2], hi[2] + 1):
                    ti.atomic_add(b.cell_count[_cell_index(b, ti.Vector([cx, cy, cz]))], 1)


@ti.kernel
def _grid_scatter(b: ti.template()):
    dims = b.grid_dims[None]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range(dims[0] * dims[1] * dims[2]):
        b.cell_count[c] = 0
    # serial: each cell lists its spheres in ascending index order (deterministic frames)
    ti.loop_config(serialize=True)
    for i in range(b.sphere_count[None]):
        lo, hi = _sphere_cells(b, i)
        for cx in range(lo[0], hi[0] + 1):
            for cy in range(lo[1], hi[1] + 1):
                for cz in range(lo[2], hi[2] + 1):
                    c = _cell_index(b, ti.Vector([cx, cy, cz]))
                    b.cell_items[b.cell_start[c] + b.cell_count[c]] = i
                    b.cell_count[c] += 1


@ti.func
def _camera_ray(b: ti.template(), i, j, height, width):
    half = b.cam_half[None]
    u = ((j + 0.5) / width * 2.0 - 1.0) * half[0]
    v = (1.0 - (i + 0.5) / height * 2.0) * half[1]
    o = b.cam_eye[None]
    d = b.cam_forward[None]
    if b.cam_ortho[None] == 1:
        o = o + u * b.cam_right[None] + v * b.cam_up[None]
    else:
        d = (d + u * b.cam_right[None] + v * b.cam_up[None]).normalized()
    return o, d


@ti.func
def _kept_interval(b: ti.template(), o, d):
    """[t_lo, t_hi] of the ray on the kept side of the cutting plane (t >= 0); t_cut: the
    plane's lower bound (-FAR when the plane does not clip the ray's start)."""
    t_lo, t_hi, t_cut = 0.0, FAR, -FAR
    if b.section_on[None] == 1:
        n = b.section_normal[None]
        s0 = (o - b.section_point[None]).dot(n)
        sd = d.dot(n)
        if sd > 0.0:
            t_cut = -s0 / sd
            t_lo = ti.max(t_lo, t_cut)
        elif sd < 0.0:
            t_hi = ti.min(t_hi, -s0 / sd)
        elif s0 < 0.0:
            t_hi = -FAR
    return t_lo, t_hi, t_cut


@ti.func
def _march(b: ti.template(), o, d, t_lo, t_hi, t_cut):
    """Nearest sphere hit in [t_lo, t_hi]: (index or -1, t, 1 if on the cut face)."""
    origin, h, dims = b.grid_origin[None], b.grid_cell[None], b.grid_dims[None]
    t0, t1 = t_lo, t_hi
    for a in ti.static(range(3)):
        top = origin[a] + dims[a] * h
        if d[a] != 0.0:
            ta = (origin[a] - o[a]) / d[a]
            tb = (top - o[a]) / d[a]
            t0 = ti.max(t0, ti.min(ta, tb))
            t1 = ti.min(t1, ti.max(ta, tb))
        elif o[a] < origin[a] or o[a] > top:
            t1 = -FAR
    best_i, best_t, best_face = -1, FAR, 0
    if t0 <= t1:
        cell = _cell_of(b, o + d * t0)
        step = ti.Vector([0, 0, 0])
        t_next = ti.Vector([FAR, FAR, FAR])
        t_delta = ti.Vector([FAR, FAR, FAR])
        for a in ti.static(range(3)):
            if d[a] > 0.0:
                step[a] = 1
                t_next[a] = (origin[a] + (cell[a] + 1) * h - o[a]) / d[a]
                t_delta[a] = h / d[a]
            elif d[a] < 0.0:
                step[a] = -1
                t_next[a] = (origin[a] + cell[a] * h - o[a]) / d[a]
                t_delta[a] = -h / d[a]
        done = False
        while not done:
            c = _cell_index(b, cell)
            for k in range(b.cell_start[c], b.cell_start[c + 1]):
                s = b.cell_items[k]
                oc = o - b.center[s]
                r = b.radius[s]
                bq = oc.dot(d)
                perp = oc - bq * d               # stable closest-approach form
                disc = r * r - perp.dot(perp)
                if disc > 0.0:
                    sq = ti.sqrt(disc)
                    t_near, t_far = -bq - sq, -bq + sq
                    t = ti.max(t_near, t_lo)
                    if t <= ti.min(t_far, t_hi) and (t < best_t or (t == best_t and s < best_i)):
                        best_i, best_t = s, t
                        best_face = 1 if t_near < t_cut else 0
            t_exit = ti.min(t_next[0], ti.min(t_next[1], t_next[2]))
            if best_t <= t_exit or t_exit > t1:
                done = True
            else:
                a = 0
                if t_next[1] < t_next[a]:
                    a = 1
                if t_next[2] < t_next[a]:
                    a = 2
                cell[a] += step[a]
                t_next[a] += t_delta[a]
                if cell[a] < 0 or cell[a] >= dims[a]:
                    done = True
    return best_i, best_t, best_face


@ti.func
def _occlusion(b: ti.template(), p, n, self_index, radius):
    """Analytic ambient occlusion at p (normal n) by spheres within `radius` of p, in [0, 1]
    (1 = unoccluded). Spheres entirely on the removed side of the cut do not occlude."""
    lo, hi = _cell_of(b, p - radius), _cell_of(b, p + radius)
    occ = 0.0
    for cx in range(lo[0], hi[0] + 1):
        for cy in range(lo[1], hi[1] + 1):
            for cz in range(lo[2], hi[2] + 1):
                c = _cell_index(b, ti.Vector([cx, cy, cz]))
                for k in range(b.cell_start[c], b.cell_start[c + 1]):
                    s = b.cell_items[k]
                    if s != self_index:
                        slo, _ = _sphere_cells(b, s)
                        first = ti.max(slo, lo)        # count each sphere in one cell only
                        if first[0] == cx and first[1] == cy and first[2] == cz:
                            r = b.radius[s]
                            dv = b.center[s] - p
                            kept = True
                            if b.section_on[None] == 1:
                                kept = (b.center[s] - b.section_point[None]).dot(
                                    b.section_normal[None]) > -r
                            l2 = dv.dot(dv)
                            if kept and l2 > 1e-30:
                                l = ti.sqrt(l2)
                                cosv = n.dot(dv) / l
                                gap = ti.max(l - r, 0.0)
                                if cosv > 0.0 and gap < radius:
                                    fall = 1.0 - gap / radius
                                    occ += cosv * ti.min(r * r / l2, 1.0) * fall * fall
    return ti.max(1.0 - AO_STRENGTH * occ, 0.0)


@ti.func
def _pixel_world(b: ti.template(), t):
    size = b.cam_pixel[None]
    if b.cam_ortho[None] == 0:
        size *= ti.max(t, 0.0)
    return size


@ti.func
def _shade(b: ti.template(), o, d, s, t, face):
    p = o + d * t
    c, r = b.center[s], b.radius[s]
    n = (p - c) / r
    albedo = b.color[s]
    if face == 1:      # flat, unlit: the cut face shows the value colour faithfully
        sn = b.section_normal[None]
        albedo *= CUT_FACE_SHADE
        # dark rim around the cut disk, about CUT_RIM_PIXELS wide
        sc = (c - b.section_point[None]).dot(sn)
        rc = ti.sqrt(ti.max(r * r - sc * sc, 0.0))
        rho = (p - (c - sc * sn)).norm()
        if rc - rho < CUT_RIM_PIXELS * _pixel_world(b, t):
            albedo *= CUT_RIM_SHADE
    col = albedo
    if face == 0:
        if n.dot(d) > 0.0:
            n = -n
        ao = _occlusion(b, p, n, s, ti.min(AO_RADIUS_FACTOR * r, b.grid_cell[None]))
        ndl = ti.max(n.dot(b.light_dir[None]), 0.0)
        col = albedo * (AMBIENT * ao + DIFFUSE * ndl * (0.5 + 0.5 * ao))
    return col


@ti.func
def _kept(b: ti.template(), p):
    keep = True
    if b.section_on[None] == 1:
        keep = (p - b.section_point[None]).dot(b.section_normal[None]) >= 0.0
    return keep


@ti.func
def _blend(col, over, alpha):
    return col * (1.0 - alpha) + over * alpha


@ti.func
def _composite_walls(b: ti.template(), o, d, t_lo, t_end, col):
    """Translucent walls hit in (t_lo, t_end), composited far to near within each wall."""
    fill = ti.Vector(WALL_COLOR)
    line = ti.Vector(WALL_LINE_COLOR)
    for w in range(b.wall_count[None]):
        pw, a = b.wall_point[w], b.wall_direction[w]
        R = b.wall_radius[w]
        if b.wall_kind[w] == PLANE:
            denom = d.dot(a)
            if ti.abs(denom) > 1e-12:
                t = (pw - o).dot(a) / denom
                if t_lo < t < t_end:
                    p = o + d * t
                    q = p - pw
                    rho = (q - q.dot(a) * a).norm()
                    if _kept(b, p) and (R <= 0.0 or rho <= R):
                        if R > 0.0 and R - rho < WALL_LINE_PIXELS * _pixel_world(b, t):
                            col = _blend(col, line, WALL_LINE_ALPHA)
                        else:
                            col = _blend(col, fill, WALL_FILL_ALPHA)
        else:
            oc = o - pw
            dp = d - d.dot(a) * a
            op = oc - oc.dot(a) * a
            qa = dp.dot(dp)
            qb = op.dot(dp)
            qc = op.dot(op) - R * R
            disc = qb * qb - qa * qc
            if qa > 1e-12 and disc > 0.0:
                sq = ti.sqrt(disc)
                for k in ti.static(range(2)):
                    t = (-qb + sq) / qa                  # far side first, then near side
                    if ti.static(k == 1):
                        t = (-qb - sq) / qa
                    if t_lo < t < t_end:
                        p = o + d * t
                        axial = (p - pw).dot(a)
                        if b.wall_lo[w] <= axial <= b.wall_hi[w] and _kept(b, p):
                            rim = ti.min(axial - b.wall_lo[w], b.wall_hi[w] - axial)
                            if rim < WALL_LINE_PIXELS * _pixel_world(b, t):
                                col = _blend(col, line, WALL_LINE_ALPHA)
                            else:
                                nrm = (p - pw - axial * a) / R
                                g = 1.0 - ti.abs(nrm.dot(d))
                                alpha = WALL_FILL_ALPHA + WALL_GRAZING_ALPHA * g ** 6
                                col = _blend(col, _blend(fill, line, g), alpha)
    return col


@ti.kernel
def _trace_image(b: ti.template()):
    height, width = b.image_size[None][0], b.image_size[None][1]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i, j in ti.ndrange(height, width):
        o, d = _camera_ray(b, i, j, height, width)
        t_lo, t_hi, t_cut = _kept_interval(b, o, d)
        s, t, face = -1, FAR, 0
        if b.sphere_count[None] > 0 and t_lo <= t_hi:
            s, t, face = _march(b, o, d, t_lo, t_hi, t_cut)
        col = b.background[None]
        if s >= 0:
            col = _shade(b, o, d, s, t, face)
        if t_lo <= t_hi:
            col = _composite_walls(b, o, d, t_lo, ti.min(t, t_hi), col)
        b.image[i, j] = ti.cast(ti.min(ti.max(col, 0.0), 1.0) * 255.0 + 0.5, ti.u8)


class Renderer:
    """Holds the device buffers and renders scenes; buffers grow (by 1.5x) only when a scene
    exceeds a capacity. Default capacities fit a 1600 x 1200 image of ~8000 spheres."""

    MIN_CAPACITY = dict(spheres=8192, cells=65536, items=262144, height=1200, width=1600)
    CELLS_PER_AXIS_MAX = 256

    def __init__(self):
        if not backend.initialized():
            backend.init()
        self.buffers: Optional[RenderBuffers] = None
        self._retired = []      # keep old buffers alive: kernels are cached per buffer object

    def _ensure(self, spheres, cells, items, height, width) -> RenderBuffers:
        b = self.buffers
        if b is not None and b.fits(spheres, cells, items, height, width):
            return b
        need = dict(spheres=spheres, cells=cells, items=items, height=height, width=width)
        have = self.MIN_CAPACITY if b is None else dict(
            spheres=b.sphere_capacity, cells=b.cell_capacity, items=b.item_capacity,
            height=b.height_capacity, width=b.width_capacity)
        cap = {k: max(have[k], int(math.ceil(1.5 * need[k])) if need[k] > have[k] else have[k])
               for k in need}
        if b is not None:
            self._retired.append(b)
        self.buffers = RenderBuffers(cap["spheres"], cap["cells"], cap["items"], cap["height"],
                                     cap["width"])
        return self.buffers

    @classmethod
    def grid_shape(cls, x, radius):
        """(origin, cell edge, dims) of the grid over the spheres' bounding box."""
        lo = np.min(x - radius[:, None], axis=0)
        hi = np.max(x + radius[:, None], axis=0)
        span = np.maximum(hi - lo, 1e-9)
        pad = 1e-6 * float(span.max())
        lo, span = lo - pad, span + 2 * pad
        cell = float(np.cbrt(np.prod(span) / len(x)))
        cell = max(cell, float(span.max()) / cls.CELLS_PER_AXIS_MAX)
        dims = np.clip(np.ceil(span / cell).astype(int), 1, cls.CELLS_PER_AXIS_MAX)
        return lo, cell, dims

    def render(self, x, radius, colors, *, width, height, camera: Camera, section=None,
               walls: Optional[WallSet] = None, background=(1.0, 1.0, 1.0)) -> np.ndarray:
        x = np.asarray(x, float).reshape(-1, 3)
        n = len(x)
        radius = np.broadcast_to(np.asarray(radius, float), (n,))
        colors = np.broadcast_to(np.asarray(colors, float), (n, 3))
        if width < 1 or height < 1:
            raise ValueError(f"image size {width}x{height} must be positive")
        if np.any(radius <= 0.0) or not np.all(np.isfinite(x)):
            raise ValueError("sphere radii must be > 0 and positions finite")
        nw = 0 if walls is None else len(walls)
        if nw > MAX_WALLS:
            raise ValueError(f"{nw} walls: the renderer draws at most {MAX_WALLS}")
        if n:
            origin, cell, dims = self.grid_shape(x, radius)
            spans = (np.floor((x + radius[:, None] - origin) / cell)
                     - np.floor((x - radius[:, None] - origin) / cell) + 1)
            items = int(np.prod(np.clip(spans, 1, dims), axis=1).sum()) + 16
        else:
            origin, cell, dims, items = np.zeros(3), 1.0, np.ones(3, int), 1
        ncells = int(np.prod(dims))
        b = self._ensure(n, ncells, items, height, width)
        self._upload(b, x, radius, colors, origin, cell, dims, camera, section, walls,
                     background, width, height)
        if n:
            _grid_count(b)
            total = exclusive_scan(b.cell_count, b.cell_start, ncells)
            if total > b.item_capacity:     # numpy estimate was short (rounding): grow, redo
                b = self._ensure(n, ncells, total, height, width)
                self._upload(b, x, radius, colors, origin, cell, dims, camera, section, walls,
                             background, width, height)
                _grid_count(b)
                exclusive_scan(b.cell_count, b.cell_start, ncells)
            _grid_scatter(b)
        _trace_image(b)
        return b.image.to_numpy()[:height, :width]

    @staticmethod
    def _upload(b, x, radius, colors, origin, cell, dims, camera, section, walls, background,
                width, height):
        dtype = backend.numpy_real()
        n = len(x)
        pad3 = np.zeros((b.sphere_capacity, 3), dtype)
        pad1 = np.zeros(b.sphere_capacity, dtype)
        pad3[:n] = x
        b.center.from_numpy(pad3)
        pad1[:n] = radius
        b.radius.from_numpy(pad1)
        pad3 = np.zeros((b.sphere_capacity, 3), dtype)
        pad3[:n] = np.clip(colors, 0.0, 1.0)
        b.color.from_numpy(pad3)
        b.sphere_count[None] = n
        b.grid_origin[None] = [float(v) for v in origin]
        b.grid_cell[None] = float(cell)
        b.grid_pad[None] = 1e-6 * float(cell)
        b.grid_dims[None] = [int(v) for v in dims]
        b.image_size[None] = [int(height), int(width)]
        f, r, u = camera.basis()
        b.cam_eye[None] = [float(v) for v in camera.eye]
        b.cam_forward[None] = f.tolist()
        b.cam_right[None] = r.tolist()
        b.cam_up[None] = u.tolist()
        b.cam_ortho[None] = 1 if camera.kind == "ortho" else 0
        half_w, half_h = camera.half_extents(width, height)
        b.cam_half[None] = [half_w, half_h]
        b.cam_pixel[None] = 2.0 * half_w / width
        b.light_dir[None] = _unit(-0.55 * f + 0.70 * u - 0.45 * r).tolist()
        b.background[None] = [float(v) for v in background]
        b.section_on[None] = 0 if section is None else 1
        if section is not None:
            b.section_point[None] = [float(v) for v in section[0]]
            b.section_normal[None] = [float(v) for v in section[1]]
        nw = 0 if walls is None else len(walls)
        b.wall_count[None] = nw
        if nw:
            kind = np.zeros(MAX_WALLS, np.int32)
            point, direction = np.zeros((MAX_WALLS, 3), dtype), np.zeros((MAX_WALLS, 3), dtype)
            rad, lo, hi = (np.zeros(MAX_WALLS, dtype) for _ in range(3))
            kind[:nw] = walls.kind
            point[:nw] = walls.point
            direction[:nw] = walls.direction / np.linalg.norm(walls.direction, axis=1)[:, None]
            rad[:nw] = walls.radius
            lo[:nw], hi[:nw] = walls.extent[:, 0], walls.extent[:, 1]
            for field, arr in ((b.wall_kind, kind), (b.wall_point, point),
                               (b.wall_direction, direction), (b.wall_radius, rad),
                               (b.wall_lo, lo), (b.wall_hi, hi)):
                field.from_numpy(arr)


_renderer: Optional[Renderer] = None


def renderer() -> Renderer:
    """The process-wide renderer (its buffers are reused from frame to frame)."""
    global _renderer
    if _renderer is None:
        _renderer = Renderer()
    return _renderer


def _particle_box(x, radius):
    if len(x) == 0:
        return np.array([-0.05, -0.05, 0.0]), np.array([0.05, 0.05, 0.1])
    return np.min(x - radius[:, None], axis=0), np.max(x + radius[:, None], axis=0)


def _resolve_camera(camera, x, radius, width, height, section) -> Camera:
    if isinstance(camera, Camera):
        return camera
    if camera is None:
        camera = "iso"
    if not isinstance(camera, str):
        raise TypeError(f"camera must be a Camera or one of {CAMERA_PRESETS}, got {camera!r}")
    if section is not None and len(x):      # frame what the cut leaves
        kept = (x - section[0]) @ section[1] > -radius
        if np.any(kept):
            x, radius = x[kept], radius[kept]
    lo, hi = _particle_box(x, radius)
    return camera_preset(camera, lo, hi, width=width, height=height, spheres=(x, radius),
                         view_normal=None if section is None else section[1])


def _render(x, radius, colors, *, width, height, camera, section, walls, background):
    """Render and also return the resolved camera and section (for overlays)."""
    x = np.asarray(x, float).reshape(-1, 3)
    radius = np.broadcast_to(np.asarray(radius, float), (len(x),))
    walls = _as_walls(walls)
    plane = resolve_section(section, x, walls)
    cam = _resolve_camera(camera, x, radius, width, height, plane)
    image = renderer().render(x, radius, colors, width=width, height=height, camera=cam,
                              section=plane, walls=walls, background=background)
    return image, cam, plane


def render_scene(x, radius, colors, *, width=1600, height=1200, camera=None, section=None,
                 walls=None, background=(1, 1, 1)) -> np.ndarray:
    """Ray-cast spheres (centres x (N,3) m, radius (N,) or scalar m, colors (N,3) in [0,1]).

    camera: a Camera, a preset name ("iso", "front", "perspective") or None ("iso").
    section: None, "xz", "yz" or (point, normal); the normal points into the kept half.
    walls: a WallSet, a dict of wall arrays (load_frame keys) or None.
    Returns the image as uint8 (height, width, 3), row 0 at the top.
    """
    return _render(x, radius, colors, width=width, height=height, camera=camera,
                   section=section, walls=walls, background=background)[0]


# ----------------------------------------------------------------------------------------------
# HDF5 states

_FRAME_DATASETS = {
    "x": ("particles/x", (0, 3), float), "v": ("particles/v", (0, 3), float),
    "w": ("particles/w", (0, 3), float), "radius": ("particles/radius", (0,), float),
    "layer": ("particles/layer", (0,), np.int32),
    "wall_kind": ("walls/kind", (0,), np.int32), "wall_point": ("walls/point", (0, 3), float),
    "wall_direction": ("walls/direction", (0, 3), float),
    "wall_radius": ("walls/radius", (0,), float), "wall_extent": ("walls/extent", (0, 2), float),
    "wall_force": ("walls/force", (0, 3), float),
    "bond_i": ("bonds/i", (0,), np.int32), "bond_j": ("bonds/j", (0,), np.int32),
    "bond_state": ("bonds/state", (0,), np.int8),
}


def _open_states(path):
    import h5py
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such states file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path}: not a readable HDF5 states file ({exc})") from None
    kind = _decode(f.attrs.get("tcd_file", "states"))
    if kind != "states":
        f.close()
        raise ValueError(f"{path}: a tcd {kind!r} file, not a states file")
    return f


def _frame_names(f) -> list:
    """Snapshot group names in time order (numeric: names grow past 6 digits after 999999)."""
    if "frames" not in f:
        return []
    return sorted(f["frames"].keys(), key=lambda name: (len(name), name))


def _single_state(path) -> bool:
    """Whether `path` is a tcd file holding one state (a prepared sample or a checkpoint),
    which renders as a file of one frame."""
    import h5py
    try:
        with h5py.File(os.fspath(path), "r") as f:
            return _decode(f.attrs.get("tcd_file", "states")) == io.FILE_CHECKPOINT
    except OSError:
        return False


def frame_count(path) -> int:
    """Number of snapshots in a states.h5 (0 when it has no frames group); 1 for a prepared
    sample or a checkpoint."""
    if _single_state(path):
        return 1
    with _open_states(path) as f:
        return len(_frame_names(f))


def _frame_of_state(path, frame) -> dict:
    """The one state of a prepared sample or checkpoint as `load_frame` gives a frame (its
    arrays checked as every state read: export.load_states)."""
    from .export import load_states
    if not isinstance(frame, (int, np.integer)) or frame not in (0, -1):
        raise ValueError(f"{path}: frame {frame} out of range (a prepared sample or checkpoint "
                         "holds one state: frame 0)")
    state = load_states(path)[0][0]
    from .export import refuse_batch
    refuse_batch(state, path, "tcd render")
    n = len(state["particles/x"])
    out = {"time": float(state.get("time", math.nan)), "step": int(state.get("step", -1)),
           "stage": str(state.get("stage", "")), "courses": _state_courses(path)}
    for key, (dataset, empty, dtype) in _FRAME_DATASETS.items():
        if dataset in state:
            out[key] = np.asarray(state[dataset], dtype)
        elif dataset.startswith("particles/") and key in _PARTICLE_DEFAULTS:
            out[key] = np.full((n,) + empty[1:], _PARTICLE_DEFAULTS[key], dtype)
        else:
            out[key] = np.zeros(empty, dtype)
    return out


def _state_courses(path):
    """The courses of a prepared sample (its meta's `courses`, since session 48) or of a run's
    checkpoint (its scenario's prepare stage); None when the file does not say."""
    try:
        meta, _ = io.checkpoint_meta(path)
    except (OSError, ValueError):
        return None
    courses = meta.get("courses")
    if isinstance(courses, list) and courses and all(isinstance(c, str) for c in courses):
        return tuple(courses)
    return scenario_courses(str(meta.get("scenario_text", "")))


def _decode(value):
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


#: particle datasets that may be absent from a frame, and their fill values
_PARTICLE_DEFAULTS = {"v": 0.0, "w": 0.0, "layer": 0}


#: the largest layer id drawn (each id below it has a row in the legend's course table)
MAX_LAYER_ID = 1000


def load_frame(path, frame: int = -1) -> dict:
    """One snapshot of a states.h5 as a flat dict of NumPy arrays (SI units); frame=-1 is the
    last one. Missing groups give empty arrays, missing particles/v, w, layer give zeros;
    a missing frame, particles/x or particles/radius, or a partial walls/bonds group raises
    ValueError naming the file and the frame."""
    path = os.fspath(path)
    if _single_state(path):
        return _frame_of_state(path, frame)
    with _open_states(path) as f:
        names = _frame_names(f)
        if not names:
            raise ValueError(f"{path}: no frames (group 'frames/' is missing or empty)")
        if not isinstance(frame, (int, np.integer)) or not -len(names) <= frame < len(names):
            raise ValueError(f"{path}: frame {frame} out of range (the file has {len(names)} "
                             f"frames, 0..{len(names) - 1})")
        name = names[int(frame)]
        where = f"{path}: frame {name}"
        g = f["frames"][name]
        out = {"time": float(_decode(g.attrs.get("time", math.nan))),
               "step": int(_decode(g.attrs.get("step", -1))),
               "stage": str(_decode(g.attrs.get("stage", ""))),
               "courses": scenario_courses(str(_decode(f.attrs.get("scenario", ""))))}
        n = len(g["particles/x"]) if "particles/x" in g else 0
        if "particles" in g and ("particles/x" not in g or "particles/radius" not in g):
            raise ValueError(f"{where}: particles/x and particles/radius are required")
        if "particles" in g:    # the schema's checks (shapes, dtypes, indices, radii, positions)
            raw = {k: v for k, v in io._datasets(g).items() if k in io.FRAME_SCHEMA}
            io.check_state(raw, where)
            layer = np.asarray(raw.get("particles/layer", np.zeros(0, int)))
            if layer.size and layer.max() > MAX_LAYER_ID:
                raise ValueError(f"{where}: key 'particles/layer' holds the layer id "
                                 f"{int(layer.max())}: at most {MAX_LAYER_ID} (a scenario has at "
                                 "most 4 courses)")
        for key, (dataset, empty, dtype) in _FRAME_DATASETS.items():
            group = dataset.split("/")[0]
            if dataset in g:
                out[key] = np.asarray(io._read(g[dataset]), dtype)    # checksum-checked
            elif group not in g:
                out[key] = np.zeros(empty, dtype)
            elif group == "particles" and key in _PARTICLE_DEFAULTS:
                out[key] = np.full((n,) + empty[1:], _PARTICLE_DEFAULTS[key], dtype)
            else:
                raise ValueError(f"{where}: dataset '{dataset}' missing")
        for prefix, keys in (("particles/", ("x", "v", "w", "radius", "layer")),
                             ("walls/", ("wall_kind", "wall_point", "wall_direction",
                                         "wall_radius", "wall_extent", "wall_force")),
                             ("bonds/", ("bond_i", "bond_j", "bond_state"))):
            lengths = {k: len(out[k]) for k in keys}
            if len(set(lengths.values())) > 1:
                raise ValueError(f"{where}: {prefix} datasets disagree in length {lengths}")
        if len(out["bond_i"]) and max(out["bond_i"].max(), out["bond_j"].max()) >= n:
            raise ValueError(f"{where}: bond particle index out of range (N = {n})")
    return out


# ----------------------------------------------------------------------------------------------
# colouring

def bond_damage(n: int, bond_i, bond_j, bond_state) -> np.ndarray:
    """Per particle fraction of its bonds that are broken (NaN for particles without bonds)."""
    bond_i, bond_j = np.asarray(bond_i, int), np.asarray(bond_j, int)
    broken = (np.asarray(bond_state) != 0).astype(float)
    total = np.bincount(bond_i, minlength=n) + np.bincount(bond_j, minlength=n)
    count = np.bincount(bond_i, broken, minlength=n) + np.bincount(bond_j, broken, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, count / np.maximum(total, 1), np.nan)[:n]


@dataclasses.dataclass(frozen=True)
class ColorScale:
    """How values map to colours: colormap name, range (in display units) and label."""
    cmap: str
    vmin: float
    vmax: float
    label: str


def particle_values(frame: dict, mode: str):
    """Values shown by a colour mode, in display units (mm/s, fraction); None for "layer"."""
    if mode not in COLOR_MODES:
        raise ValueError(f"unknown colour mode {mode!r}: expected one of {COLOR_MODES}")
    if mode == "layer":
        return None
    if mode == "speed":
        return np.linalg.norm(frame["v"], axis=1) * 1e3
    if mode == "vx":
        return frame["v"][:, 0] * 1e3
    return bond_damage(len(frame["x"]), frame["bond_i"], frame["bond_j"], frame["bond_state"])


def default_range(mode: str, values) -> Tuple[float, float]:
    if mode == "bond-damage":
        return 0.0, 1.0
    finite = np.asarray(values)[np.isfinite(values)] if values is not None else np.zeros(0)
    top = float(np.max(np.abs(finite))) if finite.size else 0.0
    top = top if top > 0.0 else 1.0
    return (-top, top) if mode == "vx" else (0.0, top)


def color_scale(mode: str, value_range) -> ColorScale:
    labels = {"speed": "speed |v| (mm/s)", "vx": "velocity $v_x$ (mm/s)",
              "bond-damage": "broken bond fraction"}
    return ColorScale(COLORMAPS[mode], float(value_range[0]), float(value_range[1]),
                      labels[mode])


def particle_colors(frame: dict, mode: str, value_range=None):
    """(colors (N,3), ColorScale or None) for a colour mode."""
    n = len(frame["x"])
    if mode == "layer":
        _, table = _courses(frame)
        layer = np.clip(np.asarray(frame["layer"], int), 0, len(table) - 1)
        # a small per-grain brightness jitter (fixed by index) keeps touching grains apart
        jitter = 1.0 + 0.10 * (((np.arange(n) * 2654435761) % 1000) / 1000.0 - 0.5)
        return np.clip(LAYER_COLORS[table[layer]] * jitter[:, None], 0, 1), None
    values = particle_values(frame, mode)
    lo, hi = default_range(mode, values) if value_range is None else value_range
    scale = color_scale(mode, (lo, hi))
    return value_colors(values, scale.cmap, lo, hi), scale


def _courses(frame: dict) -> tuple[tuple, np.ndarray]:
    """The course kind of each layer id of `frame` (its prepare stage's `courses`; layer ids
    past them, or a frame without its scenario, read as DEFAULT_COURSES, then "layer k"),
    and each one's row of LAYER_COLORS."""
    courses = tuple(frame.get("courses") or DEFAULT_COURSES)
    top = int(np.max(frame["layer"])) + 1 if len(frame["layer"]) else 0
    kinds = courses + tuple(f"layer {k}" for k in range(len(courses), top))
    return kinds, np.array([COURSE_COLOR.get(kind, 1) for kind in kinds], int)


def layer_legend(frame: dict) -> list:
    """[(label, rgb)] of the courses present in `frame`, from the top course down, a kind
    listed once."""
    kinds, table = _courses(frame)
    present = sorted(set(np.clip(np.asarray(frame["layer"], int), 0, len(kinds) - 1).tolist()),
                     reverse=True)
    legend = {}
    for k in present:
        label = f"{kinds[k]} course" if kinds[k] in COURSE_COLOR else kinds[k]
        legend.setdefault(label, LAYER_COLORS[table[k]])
    return list(legend.items())


@functools.lru_cache(maxsize=8)     # one parse per file, not one per frame of an animation
def scenario_courses(text: str):
    """`courses` of the first prepare stage of the scenario TOML `text` (None if it has none
    or cannot be read)."""
    import tomllib
    try:
        stages = tomllib.loads(text).get("stage", [])
    except (tomllib.TOMLDecodeError, TypeError, AttributeError):
        return None
    for stage in stages if isinstance(stages, list) else []:
        if isinstance(stage, dict) and stage.get("kind") == "prepare":
            courses = stage.get("courses", list(DEFAULT_COURSES))
            if isinstance(courses, list) and all(isinstance(c, str) for c in courses):
                return tuple(courses)
    return None


def value_colors(values, cmap: str, lo: float, hi: float) -> np.ndarray:
    """Colours (N,3) of `values` on colormap `cmap` over [lo, hi] (clipped at both ends);
    non-finite values (a grain without bonds) get NO_BOND_COLOR."""
    import matplotlib
    unit = (values - lo) / (hi - lo if hi > lo else 1.0)
    colors = matplotlib.colormaps[cmap](np.clip(np.nan_to_num(unit), 0, 1))[:, :3]
    colors[~np.isfinite(values)] = NO_BOND_COLOR
    return colors


# ----------------------------------------------------------------------------------------------
# overlays (matplotlib, Agg) and files

def _nice_length(target: float) -> float:
    """1, 2 or 5 x 10^k not above target (> 0)."""
    k = math.floor(math.log10(target))
    for m in (5.0, 2.0, 1.0):
        if m * 10**k <= target:
            return m * 10**k
    return 10**k


def annotate(image: np.ndarray, *, scale: Optional[ColorScale] = None, legend=None,
             metres_per_pixel: Optional[float] = None, title: Optional[str] = None) -> np.ndarray:
    """Composite a colour bar, a legend [(label, rgb)], a scale bar and a title over an image
    (uint8 (H,W,3)); returns a new uint8 (H,W,3) array of the same size."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    import matplotlib

    h, w = image.shape[:2]
    dpi = 100.0
    fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    fig.figimage(image, 0, 0, origin="upper", zorder=-1)     # below every overlay
    font = max(5.0, 13.0 * min(w / 1600.0, h / 1200.0) ** 0.7)
    if scale is not None:
        cax = fig.add_axes([1.0 - 0.72 * COLORBAR_STRIP, 0.25, 0.022, 0.5])
        norm = matplotlib.colors.Normalize(scale.vmin, scale.vmax)
        cb = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=scale.cmap), cax=cax)
        cb.set_label(scale.label, fontsize=font)
        cb.ax.tick_params(labelsize=0.85 * font)
    if legend:
        from matplotlib.patches import Patch
        handles = [Patch(facecolor=tuple(rgb), edgecolor="0.2", label=label)
                   for label, rgb in legend]
        fig.legend(handles=handles, loc="upper right", fontsize=font, frameon=False)
    if metres_per_pixel:
        length = _nice_length(0.18 * w * metres_per_pixel)
        px = length / metres_per_pixel
        x0, y0 = 0.04 * w, 0.05 * h
        ax = fig.add_axes([0, 0, 1, 1])
        ax.set_axis_off()
        ax.set_xlim(0, w)
        ax.set_ylim(0, h)
        ax.plot([x0, x0 + px], [y0, y0], color="k", lw=max(1.5, h / 300.0),
                solid_capstyle="butt")
        ax.text(x0 + 0.5 * px, y0 + 0.012 * h, f"{length * 1e3:g} mm", ha="center",
                va="bottom", fontsize=font)
    if title:
        fig.text(0.02, 0.98, title, ha="left", va="top", fontsize=font)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:, :, :3].copy()


@contextlib.contextmanager
def atomic_output(out):
    """Yield a temporary path in out's directory (created if need be), with out's extension;
    on success it replaces `out` (io.atomic_path: fsync, then os.replace), on failure it is
    removed: a killed render never leaves half a file."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(out, suffix=out.suffix) as tmp:
        yield tmp


def write_image(image: np.ndarray, out) -> None:
    """Write an image atomically (format from the extension, via imageio)."""
    import imageio.v3 as iio
    with atomic_output(out) as tmp:
        iio.imwrite(tmp, image, extension=Path(out).suffix)


def _frame_title(frame: dict) -> str:
    stage = f"  {frame['stage']}" if frame.get("stage") else ""
    return f"t = {frame['time']:.4g} s{stage}"


def render_area_width(width: int, colorbar: bool) -> int:
    """Width of the area the spheres are drawn in: the image less the colour bar's strip."""
    return max(1, int(round(width * (1.0 - COLORBAR_STRIP)))) if colorbar else width


def render_frame(frame: dict, *, color="layer", section=None, camera="iso", width=1600,
                 height=1200, colorbar=True, value_range=None, walls=True) -> np.ndarray:
    """Render a snapshot (a load_frame dict) coloured by `color` (one of COLOR_MODES).

    colorbar: composite the colour bar (or layer legend), scale bar (orthographic cameras) and
    time label. value_range: (vmin, vmax) in display units (mm/s; fraction for bond-damage),
    default from the frame. walls: draw the frame's walls.
    """
    colors, scale = particle_colors(frame, color, value_range)
    # keep a white strip on the right for the bar
    render_width = render_area_width(width, colorbar and scale is not None)
    image, cam, _ = _render(frame["x"], frame["radius"], colors, width=render_width,
                            height=height, camera=camera, section=section,
                            walls=WallSet.from_frame(frame) if walls else None,
                            background=(1.0, 1.0, 1.0))
    if not colorbar:
        return image
    if render_width < width:
        strip = np.full((height, width - render_width, 3), 255, np.uint8)
        image = np.concatenate([image, strip], axis=1)
    legend = None
    if color == "layer":
        legend = layer_legend(frame)
    elif color == "bond-damage" and np.isnan(particle_values(frame, color)).any():
        legend = [("no bonds", NO_BOND_COLOR)]
    return annotate(image, scale=scale, legend=legend, title=_frame_title(frame),
                    metres_per_pixel=(cam.pixel_size(render_width, height)
                                      if cam.kind == "ortho" else None))


def _frame_list(path, frames):
    n = frame_count(path)
    if isinstance(frames, str):
        if frames != "all":
            raise ValueError(f"frames={frames!r}: expected 'all' or a sequence of indices")
        return list(range(n))
    return [int(k) for k in frames]


#: the highest frame rate a GIF plays as asked: its delays are hundredths of a second, and
#: browsers and viewers play a delay under 0.02 s as 0.1 s
MAX_GIF_FPS = 50


class WriterMissing(RuntimeError):
    """The image or animation format asked for needs a package that is not installed."""


def _check_animation_writer(out: Path):
    if out.suffix.lower() == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise WriterMissing(
            f"cannot write {out}: MP4 output needs the 'imageio-ffmpeg' package, which is not "
            f"installed (pip install imageio-ffmpeg); or write a GIF instead, e.g. "
            f"--out {out.with_suffix('.gif').name}")


def render_file(path, out, *, frame=-1, frames=None, color="layer", section=None, camera="iso",
                width=1600, height=1200, fps=10) -> None:
    """Render a states.h5 to an image (out *.png: one frame) or an animation (out *.gif or
    *.mp4: `frames`, "all" by default, one colour scale for all frames). Written atomically."""
    out = Path(out)
    check_output(out)
    animate = out.suffix.lower() in ANIMATION_EXTENSIONS
    if not animate:
        if frames is not None:
            raise ValueError(f"frames={frames!r} needs an animation output (.gif or .mp4), "
                             f"got {out}")
        write_image(render_frame(load_frame(path, frame), color=color, section=section,
                                 camera=camera, width=width, height=height), out)
        return
    _check_animation_writer(out)
    if out.suffix.lower() == ".gif" and fps > MAX_GIF_FPS:
        raise ValueError(f"--fps {fps:g}: a GIF keeps each frame's delay in hundredths of a "
                         "second, and viewers play delays under 0.02 s at about 10 frames per "
                         f"second: at most {MAX_GIF_FPS} frames per second in a GIF (an .mp4 "
                         "takes more)")
    indices = _frame_list(path, "all" if frames is None else frames)
    if not indices:
        raise ValueError(f"{path}: no frames to animate")
    scaled = color != "layer"     # a colour scale (and its bar's strip), not the layers' legend
    value_range = None
    if scaled:     # one colour scale over the whole animation
        values = [particle_values(load_frame(path, k), color) for k in indices]
        value_range = default_range(color, np.concatenate(values))
    if camera in CAMERA_PRESETS:     # one camera over the whole animation: frame the first one
        first = load_frame(path, indices[0])
        walls = WallSet.from_frame(first)
        plane = resolve_section(section, first["x"], walls)
        # framed for the area the frames are drawn in (a perspective camera framed for the
        # whole width cut the grains off at the colour bar's strip, and zoomed 13 % closer
        # than the same frame rendered alone: session 44's audit)
        camera = _resolve_camera(camera, first["x"], first["radius"],
                                 render_area_width(width, scaled), height, plane)
    with atomic_output(out) as tmp:
        if out.suffix.lower() == ".gif":
            import imageio.v3 as iio
            writer = iio.imopen(tmp, "w", extension=".gif")

            def append(image):
                writer.write(image, duration=1000.0 / fps, loop=0)
        else:
            import imageio.v2 as iio2
            writer = iio2.get_writer(tmp, format="FFMPEG", mode="I", fps=fps)
            append = writer.append_data
        with writer:
            for k in indices:
                append(render_frame(load_frame(path, k), color=color, section=section,
                                    camera=camera, width=width, height=height,
                                    value_range=value_range))


def figure_sample(path, out, frame=0, *, width=1600, height=1200) -> None:
    """Paper Fig. 2: the prepared sample, two layers in two colours, perspective view."""
    write_image(render_frame(load_frame(path, frame), color="layer", camera="perspective",
                             width=width, height=height), out)


def driving_speed(frames: list) -> float:
    """Speed (m/s) of the fastest-moving wall between the first and the last of `frames`
    (loaded frames with the same walls): the imposed velocity of the shear ring. 0.0 when
    there is one frame, no time between them, or no wall moved."""
    if len(frames) < 2:
        return 0.0
    a, b = frames[0], frames[-1]
    dt = b["time"] - a["time"]
    pa, pb = np.asarray(a["wall_point"]), np.asarray(b["wall_point"])
    if not (dt > 0.0) or pa.shape != pb.shape or not len(pa):
        return 0.0
    return float(np.max(np.linalg.norm(pb - pa, axis=1)) / dt)


def ring_offset(frame: dict) -> float:
    """Largest horizontal offset (m) of a cylinder's axis from the vertical z axis in a frame:
    how far the shear ring has moved (the mould and the rings start on the z axis)."""
    kind, point = np.asarray(frame["wall_kind"]), np.asarray(frame["wall_point"])
    cyl = kind == CYLINDER
    return float(np.max(np.hypot(point[cyl, 0], point[cyl, 1]))) if np.any(cyl) else 0.0


VELOCITY_RANGE = (0.0, 1.25)     # v_x / v_ring shown in Fig. 3: at rest .. the ring, and a bit
ARROW_CAP = 3.0                  # arrows of grains faster than this many ring speeds are capped


#: what Fig. 3 shows of the grains' motion: "mean" (the paper's "average velocity of grains":
#: each grain's displacement from a frame to the next over their time apart) or "instant" (the
#: velocities the frame holds, at the end of one time step)
VELOCITY_KINDS = ("mean", "instant")


def mean_velocity(path, k: int, frame: dict) -> tuple[dict, str]:
    """Frame `k` of `path` (loaded: `frame`) with each grain's velocity replaced by its mean
    over the interval to the next frame, or from the previous one when `k` is the last of its
    stage: the displacement over the time between the two frames (the grains' order is that
    of the stage's simulation, the same in both). Returns it and a phrase naming the interval
    ("to frame 12, ring 2.39 mm"); the frame as it is and "" where no frame of the same stage
    and grains lies next to it."""
    count = frame_count(path)
    for other in (k + 1, k - 1):
        if not 0 <= other < count:
            continue
        nb = load_frame(path, other)
        if nb["stage"] != frame["stage"] or nb["x"].shape != frame["x"].shape:
            continue
        (a, b) = (frame, nb) if other > k else (nb, frame)
        dt = b["time"] - a["time"]
        if not dt > 0.0:
            continue
        out = dict(frame)
        out["v"] = (b["x"] - a["x"]) / dt
        where = f"ring {ring_offset(nb) * 1e3:.2f} mm" if ring_offset(nb) > 0.0 else \
            f"t = {nb['time']:.4g} s"
        return out, f"{'to' if other > k else 'from'} frame {other}, {where}"
    return frame, ""


def figure_velocity(path, out, frames, *, panel_width=900, velocity: str = "mean") -> None:
    """Paper Fig. 3: the velocity field on the vertical section through the axis (xz) at the
    given frames (e.g. early in the shear and at failure), panels side by side, one colour bar.
    `velocity`: "mean", the paper's "average velocity of grains", each grain's displacement
    from the frame to the next over their time apart (`mean_velocity`; a study's snapshots
    0.25 s apart average over 0.21 mm of the ring's travel), or "instant", the velocities the
    frame holds: at failure a bond cascade's elastic rebound and rattling small grains move
    faster than the ring there, so the instant field hides the two blocks the mean shows.

    When a wall moves between the first and the last frame (the shear ring), the colour is each
    grain's velocity along x over the ring's speed (0: at rest, 1: moving with the ring; the
    paper's "upper half moves as one block"), and the arrows of (vx, vz) for the grains cut by
    the section share one scale, the ring's speed as reference, capped at ARROW_CAP ring speeds
    (free small grains falling through the pores move at up to ~1 m/s, 1000 ring speeds).
    Otherwise the colour is the speed up to its 99th percentile and the arrows are scaled per
    panel."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    import matplotlib

    if velocity not in VELOCITY_KINDS:
        raise ValueError(f"velocity {velocity!r}: expected one of {', '.join(VELOCITY_KINDS)}")
    loaded = [load_frame(path, k) for k in frames]
    if not loaded:
        raise ValueError("figure_velocity needs at least one frame")
    ring = driving_speed(loaded)
    windows = [""] * len(loaded)       # over which interval each panel's mean was taken
    if velocity == "mean":
        for i, k in enumerate(frames):
            loaded[i], windows[i] = mean_velocity(path, int(k) % frame_count(path), loaded[i])
    if ring > 0.0:
        mode, cmap, value_range = "vx", "viridis", VELOCITY_RANGE
        label = (f"{'mean ' if velocity == 'mean' else ''}$v_x$ / ring speed "
                 f"(ring: {ring * 1e3:.3g} mm/s)")
        values = [fr["v"][:, 0] / ring for fr in loaded]
    else:
        speeds = [particle_values(fr, "speed") for fr in loaded]
        every = np.concatenate(speeds)
        finite = every[np.isfinite(every)]
        # the colour scale ends at the 99th percentile: a few free small grains falling through
        # the pores (up to ~1 m/s) would otherwise leave the whole sample at the bottom colour
        top = float(np.percentile(finite, 99)) if finite.size else 0.0
        mode, cmap = "speed", COLORMAPS["speed"]
        value_range = (0.0, top) if top > 0.0 else default_range("speed", every)
        label = "speed |v| (mm/s), top: 99th percentile"
        values = speeds
    first = loaded[0]
    walls = WallSet.from_frame(first)
    plane = resolve_section("xz", first["x"], walls)
    lo, hi = _particle_box(first["x"], first["radius"])
    aspect = (hi[2] - lo[2]) / max(hi[0] - lo[0], 1e-9)
    width, height = panel_width, max(64, int(round(panel_width * aspect)))
    cam = camera_preset("front", lo, hi, width=width, height=height, view_normal=plane[1],
                        spheres=(first["x"], first["radius"]))
    _, right, up = cam.basis()
    half_w, half_h = cam.half_extents(width, height)
    centre = np.asarray(cam.target)
    c_u, c_v = float(centre @ right), float(centre @ up)
    extent = np.array([c_u - half_w, c_u + half_w, c_v - half_h, c_v + half_h]) * 1e3

    fig = Figure(figsize=(5.2 * len(loaded) + 1.2, 5.2 * aspect + 0.9), dpi=150,
                 layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(loaded), squeeze=False)[0]
    for ax, fr, k, vals, window in zip(axes, loaded, frames, values, windows):
        colors = value_colors(vals, cmap, *value_range)
        image, _, _ = _render(fr["x"], fr["radius"], colors, width=width, height=height,
                              camera=cam, section=plane, walls=WallSet.from_frame(fr),
                              background=(1, 1, 1))
        ax.imshow(image, extent=extent, interpolation="antialiased")
        dist = (fr["x"] - plane[0]) @ plane[1]
        near = np.abs(dist) < fr["radius"]
        if np.any(near):
            pu, pv = fr["x"][near] @ right * 1e3, fr["x"][near] @ up * 1e3
            vu, vv = fr["v"][near] @ right, fr["v"][near] @ up
            length = np.hypot(vu, vv)
            if ring > 0.0:      # one scale for all panels: the ring's speed is 5 % of the width
                cap = np.maximum(length / (ARROW_CAP * ring), 1.0)
                vu, vv = vu / cap, vv / cap
                ref, key, span, x_key = ring, "ring speed", (ring, 0.05), 0.78
            else:               # per panel: the fastest grain's arrow is 6 % of the width
                vmax = float(np.max(length))
                ref = _nice_length(vmax) if vmax > 0.0 else 0.0
                key, span, x_key = f"{ref * 1e3:g} mm/s", (vmax, 0.06), 0.80
            if ref > 0.0:
                q = ax.quiver(pu, pv, vu, vv, angles="xy", scale_units="xy",
                              scale=span[0] / (span[1] * (extent[1] - extent[0])), width=0.004,
                              color="k", alpha=0.8)
                ax.quiverkey(q, x_key, 1.03, ref, key, labelpos="E", coordinates="axes",
                             fontproperties={"size": 8})
        if ring > 0.0:
            title = f"frame {k}: ring moved {ring_offset(fr) * 1e3:.2f} mm (t = {fr['time']:.4g} s)"
        else:
            title = f"frame {k}: {_frame_title(fr)}"
        if velocity == "mean":
            title += (f";\nmean velocity {window}" if window else
                      ";\ninstant velocity (no frame next to it)")
        ax.set_title(title, fontsize=9, loc="left")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z (mm)")
    norm = matplotlib.colors.Normalize(*value_range)
    cb = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap),
                      ax=list(axes), shrink=0.9, extend="both" if mode == "vx" else "max")
    cb.set_label(label)
    if ring > 0.0:
        what = ("mean velocity (displacement from a snapshot to the next over their time "
                "apart)" if velocity == "mean" else "velocity")
        fig.suptitle(f"{what} of the grains cut by the vertical section through the axis;\n"
                     f"arrows ($v_x$, $v_z$) on one scale, capped at {ARROW_CAP:g} ring speeds",
                     fontsize=9)
    with atomic_output(out) as tmp:
        fmt = Path(out).suffix.lstrip(".") or "png"
        io.save_figure(fig, tmp, fmt)


# ----------------------------------------------------------------------------------------------
# reference scene for the regression test

REFERENCE_IMAGE = Path(__file__).resolve().parent.parent / "tests" / "data" / "render_reference.png"


def reference_scene():
    """The tiny fixed scene of tests/data/render_reference.png: five spheres in a cylinder
    with a bottom plate, perspective camera, 64 x 48 pixels."""
    x = np.array([[0.0, 0.0, 0.010], [0.012, 0.004, 0.008], [-0.010, -0.006, 0.006],
                  [0.002, -0.010, 0.022], [-0.004, 0.010, 0.018]])
    radius = np.array([0.010, 0.008, 0.006, 0.005, 0.007])
    colors = np.array([[0.8, 0.3, 0.2], [0.2, 0.6, 0.3], [0.2, 0.3, 0.8], [0.9, 0.8, 0.2],
                       [0.6, 0.6, 0.6]])
    walls = WallSet(kind=np.array([PLANE, CYLINDER]), point=np.zeros((2, 3)),
                    direction=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]),
                    radius=np.array([0.024, 0.024]), extent=np.array([[0, 0], [0.0, 0.03]]))
    camera = Camera("perspective", eye=(0.05, -0.08, 0.07), target=(0.0, 0.0, 0.012),
                    fov_deg=40.0)
    return dict(x=x, radius=radius, colors=colors, walls=walls, camera=camera, width=64,
                height=48)


def render_reference() -> np.ndarray:
    s = reference_scene()
    return render_scene(s["x"], s["radius"], s["colors"], width=s["width"], height=s["height"],
                        camera=s["camera"], walls=s["walls"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tcd.render", description=__doc__.split("\n")[0])
    parser.add_argument("--regen-reference", action="store_true",
                        help=f"rewrite {REFERENCE_IMAGE} from reference_scene() (CPU, f64)")
    args = parser.parse_args(argv)
    if not args.regen_reference:
        parser.print_help()
        return 0
    backend.init("cpu", "f64")
    write_image(render_reference(), REFERENCE_IMAGE)
    print(f"wrote {REFERENCE_IMAGE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
