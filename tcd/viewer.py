"""Interactive viewer of a states.h5: a Taichi GGUI window (needs a display and Vulkan).

Controls: right mouse button + drag or WASD/QE orbit and move the camera (GGUI's
`track_user_inputs`); Left/Right arrows or the slider step through the frames; Space plays and
pauses; C cycles the colour mode (layer, speed, vx, bond-damage); Escape closes the window.
Frames are read from the file on demand, the colours come from `tcd.render.particle_colors`.
Headless machines (no DISPLAY / WAYLAND_DISPLAY, or no Vulkan) get a RuntimeError that points
to the offscreen renderer (`tcd render FILE.h5 --out image.png`).
"""
import os

import numpy as np
import taichi as ti

from . import backend, render

_HEADLESS_HELP = ("the interactive viewer uses Taichi GGUI, which needs a display and a Vulkan "
                  "driver{detail}; render offscreen instead: tcd render FILE.h5 --out image.png")


def _require_display() -> None:
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise RuntimeError(_HEADLESS_HELP.format(detail=" (DISPLAY and WAYLAND_DISPLAY are unset)"))


def _open_window(title: str, size):
    try:
        return ti.ui.Window(title, size, vsync=True)
    except Exception as exc:  # GGUI raises plain RuntimeErrors for missing Vulkan/display
        raise RuntimeError(_HEADLESS_HELP.format(detail=f" (window creation failed: {exc})")) from exc


def view(path, *, frame: int = -1, color: str = "layer", size=(1280, 960)) -> None:
    """Open an interactive window on the snapshots of `path` (a states.h5)."""
    count = render.frame_count(path)           # file errors before any window is opened
    if count == 0:
        raise ValueError(f"{path}: no frames to view")
    _require_display()
    if not backend.initialized():
        backend.init()
    window = _open_window(f"tcd: {os.path.basename(os.fspath(path))}", size)

    current = frame % count
    data = render.load_frame(path, current)
    n = max(len(data["x"]), 1)
    # GGUI only accepts 32-bit float fields: the one place tcd names ti.f32 on purpose
    centers = ti.Vector.field(3, ti.f32, shape=n)
    radii = ti.field(ti.f32, shape=n)
    colors = ti.Vector.field(3, ti.f32, shape=n)
    modes = list(render.COLOR_MODES)
    mode = modes.index(color)

    def upload(fr, capacity):
        k = len(fr["x"])
        if k > capacity:
            raise ValueError(f"{path}: frame has {k} particles, more than the first frame's "
                             f"{capacity}; the viewer keeps a fixed particle count")
        pad = np.zeros((capacity, 3), np.float32)
        pad[:k] = fr["x"]
        centers.from_numpy(pad)
        rad = np.zeros(capacity, np.float32)
        rad[:k] = fr["radius"]
        radii.from_numpy(rad)
        col, _ = render.particle_colors(fr, modes[mode])
        pad = np.zeros((capacity, 3), np.float32)
        pad[:k] = col
        colors.from_numpy(pad)
        return k

    shown = upload(data, n)
    lo, hi = render._particle_box(data["x"], data["radius"])
    preset = render.camera_preset("perspective", lo, hi, width=size[0], height=size[1])
    scene = ti.ui.Scene()
    camera = ti.ui.Camera()
    camera.position(*preset.eye)
    camera.lookat(*preset.target)
    camera.up(*preset.up)
    camera.fov(preset.fov_deg)
    canvas = window.get_canvas()
    gui = window.get_gui()
    playing = False
    speed = float(np.linalg.norm(np.subtract(hi, lo))) * 0.5

    while window.running:
        wanted = current
        for event in window.get_events(ti.ui.PRESS):
            if event.key == ti.ui.ESCAPE:
                window.running = False
            elif event.key == ti.ui.LEFT:
                wanted = max(current - 1, 0)
            elif event.key == ti.ui.RIGHT:
                wanted = min(current + 1, count - 1)
            elif event.key == ti.ui.SPACE:
                playing = not playing
            elif event.key in ("c", "C"):
                mode = (mode + 1) % len(modes)
                shown = upload(data, n)
        if playing:
            wanted = (current + 1) % count
        with gui.sub_window("frames", 0.02, 0.02, 0.4, 0.16):
            wanted = gui.slider_int("frame", wanted, 0, count - 1)
            gui.text(f"t = {data['time']:.4g} s  {data['stage']}  colour: {modes[mode]}")
        if wanted != current:
            current = wanted
            data = render.load_frame(path, current)
            shown = upload(data, n)
        camera.track_user_inputs(window, movement_speed=0.02 * speed, hold_key=ti.ui.RMB)
        scene.set_camera(camera)
        scene.ambient_light((0.35, 0.35, 0.35))
        scene.point_light(pos=tuple(np.asarray(preset.eye) + [0.0, 0.0, speed]), color=(1, 1, 1))
        scene.particles(centers, radius=0.001, per_vertex_color=colors, per_vertex_radius=radii,
                        index_count=shown)
        canvas.set_background_color((1.0, 1.0, 1.0))
        canvas.scene(scene)
        window.show()
