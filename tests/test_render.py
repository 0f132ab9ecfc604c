"""Offscreen renderer: geometry of the ray casting, cutting plane, reference image, files.

Pixel tests use orthographic cameras with 1 mm pixels, so the projected disk of a sphere is
known analytically: pixel (i, j) has its centre at x = (j + 0.5 - W/2) mm, y = (H/2 - i - 0.5) mm
in the camera's right/up coordinates. Background is pure white; sphere colours are pure
primaries, so "sphere" and "background" pixels are told apart exactly.
"""
import importlib.util
from pathlib import Path

import h5py
import imageio.v3 as iio
import numpy as np
import pytest

from tcd import render
from tcd.render import Camera

W, H, PX = 64, 48, 1e-3
RED, GREEN, BLUE = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


@pytest.fixture(scope="module", autouse=True)
def _tcd_backend_render(request):
    """The session's backend (conftest: --arch, --precision)."""
    request.getfixturevalue("backend")


def top_camera():
    """Looks down -z; image right = +x, image up = +y."""
    return Camera("ortho", eye=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                  ortho_width=W * PX)


def front_camera():
    """Looks along +y from y = -1 m; image right = +x, image up = +z."""
    return Camera("ortho", eye=(0.0, -1.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
                  ortho_width=W * PX)


def pixel_centres():
    j, i = np.meshgrid(np.arange(W), np.arange(H))
    return (j + 0.5 - W / 2) * PX, (H / 2 - i - 0.5) * PX


def disk_masks(cu, cv, r):
    """(inside by more than a pixel, outside by more than a pixel) of a projected disk."""
    u, v = pixel_centres()
    dist = np.hypot(u - cu, v - cv)
    return dist < r - PX, dist > r + PX


def background(img):
    return np.all(img == 255, axis=-1)


def draw(x, radius, colors, **kw):
    kw.setdefault("camera", top_camera())
    return render.render_scene(np.asarray(x, float), np.asarray(radius, float),
                               np.asarray(colors, float), width=W, height=H, **kw)


def test_single_sphere_covers_its_projected_disk():
    c, r = (0.0031, -0.0042, 0.002), 0.0105
    img = draw([c], [r], [RED])
    inside, outside = disk_masks(c[0], c[1], r)
    assert inside.sum() > 250
    assert not background(img)[inside].any()
    assert background(img)[outside].all()
    sphere = ~background(img)
    assert np.all(img[sphere][:, 1:] == 0), "a red sphere shades to shades of red only"
    # Lambert shading: the lit side (light comes from the upper left) is brighter than the other
    u, v = pixel_centres()
    upper_left = inside & (u < c[0] - 0.5 * r) & (v > c[1] + 0.3 * r)
    lower_right = inside & (u > c[0] + 0.5 * r) & (v < c[1] - 0.3 * r)
    assert img[upper_left][:, 0].mean() > img[lower_right][:, 0].mean() + 40


def test_nearer_sphere_is_seen_where_two_overlap():
    a, b = (-0.004, 0.0, 0.0), (0.004, 0.0, 0.005)        # b is nearer to the camera (+z)
    r = 0.008
    overlap = disk_masks(a[0], a[1], r)[0] & disk_masks(b[0], b[1], r)[0]
    assert overlap.sum() > 30
    img = draw([a, b], [r, r], [RED, GREEN])
    assert np.all(img[overlap][:, 1] > 0) and np.all(img[overlap][:, 0] == 0)
    # index order does not matter, depth does
    swapped = draw([b, a], [r, r], [GREEN, RED])
    np.testing.assert_array_equal(img, swapped)
    a_near = draw([(a[0], a[1], 0.01), b], [r, r], [RED, GREEN])
    assert np.all(a_near[overlap][:, 0] > 0) and np.all(a_near[overlap][:, 1] == 0)


def test_section_removes_what_lies_in_front_and_shows_cut_faces():
    r = 0.008
    front = (-0.018, -0.02, 0.0)       # entirely in y < 0: removed
    cut = (0.0, 0.0, 0.0)              # centre on the plane: half removed, cut face shown
    back = (0.018, 0.02, 0.0)          # entirely in y > 0: untouched
    x, radius, colors = [front, cut, back], [r, r, r], [RED, GREEN, BLUE]
    plane = ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    whole = draw(x, radius, colors, camera=front_camera())
    sliced = draw(x, radius, colors, camera=front_camera(), section=plane)
    masks = {name: disk_masks(p[0], p[2], r)[0] for name, p in
             (("front", front), ("cut", cut), ("back", back))}
    assert not background(whole)[masks["front"]].any()
    assert background(sliced)[masks["front"]].all(), "sphere in front of the plane is removed"
    np.testing.assert_array_equal(sliced[masks["back"]], whole[masks["back"]])
    # the cut face: a flat disk of the sphere's full radius in the sphere's own colour, the
    # colour bar's (session 44: it was 0.88 of it, and values read off the bar were 12 % off)
    face = sliced[disk_masks(cut[0], cut[2], r - 1.5 * PX)[0]]
    assert np.all(face[:, 1] == 255) and np.all(face[:, [0, 2]] == 0)
    # without the cut, the same pixels show a shaded sphere (not flat)
    shaded = whole[disk_masks(cut[0], cut[2], r - 1.5 * PX)[0]][:, 1]
    assert shaded.max() - shaded.min() > 60
    # the string form "xz" is the same plane through the axis (no walls: box centre at y = 0)
    named = draw(x, radius, colors, camera=front_camera(), section="xz")
    np.testing.assert_array_equal(named, sliced)


def test_perspective_projection_matches_camera_project():
    cam = Camera("perspective", eye=(0.1, -0.2, 0.15), target=(0.0, 0.0, 0.0), fov_deg=30.0)
    x = np.array([[0.0, 0.0, 0.0], [0.03, 0.02, -0.01]])
    img = draw(x, [0.004, 0.004], [RED, BLUE], camera=cam)
    (c0, r0), (c1, r1) = cam.project(x, W, H)[0].astype(int)
    assert img[r0, c0, 0] > 0 and img[r0, c0, 2] == 0
    assert img[r1, c1, 2] > 0 and img[r1, c1, 0] == 0


def test_walls_are_translucent_and_outlined():
    walls = render.WallSet(kind=np.array([render.CYLINDER]), point=np.zeros((1, 3)),
                               direction=np.array([[0.0, 0.0, 1.0]]), radius=np.array([0.02]),
                               extent=np.array([[-0.015, 0.015]]))
    img = draw([(0.0, 0.0, 0.0)], [0.008], [RED], camera=front_camera(), walls=walls)
    u, v = pixel_centres()
    between = (np.abs(u) > 0.01) & (np.abs(u) < 0.018) & (np.abs(v) < 0.01)
    assert np.all(img[between] < 255) and np.all(img[between] > 200), "thin translucent veil"
    rim = (np.abs(np.abs(v) - 0.015) < 0.5 * PX) & (np.abs(u) < 0.015)
    assert img[rim].max() < 120, "rims drawn as dark lines"
    assert np.all(img[np.abs(u) > 0.022] == 255)


def test_matches_reference_image():
    path = render.REFERENCE_IMAGE
    assert path.is_file(), f"{path} missing: run `python -m tcd.render --regen-reference`"
    ref = iio.imread(path)[:, :, :3].astype(int)
    img = render.render_reference().astype(int)
    assert img.shape == ref.shape
    diff = np.abs(img - ref)
    assert diff.mean() < 2.0 and diff.max() < 40, (diff.mean(), diff.max())


def test_buffers_are_reused_between_frames():
    draw([(0.0, 0.0, 0.0)], [0.01], [RED])
    buffers = render.renderer().buffers
    draw([(0.0, 0.0, 0.0), (0.01, 0.0, 0.0)], [0.01, 0.005], [RED, BLUE])
    assert render.renderer().buffers is buffers


def test_bond_damage_is_broken_fraction_per_particle():
    damage = render.bond_damage(4, [0, 1, 0], [1, 2, 2], [0, 2, 1])
    np.testing.assert_allclose(damage[:3], [0.5, 0.5, 1.0])
    assert np.isnan(damage[3])


# ---------------------------------------------------------------------------------------------
# files

def write_states(path, frames=3, n=40, seed=0):
    """A small states.h5 following the schema (frames drift upward, bonds break over time)."""
    rng = np.random.default_rng(seed)
    x0 = np.column_stack([rng.uniform(-0.02, 0.02, n), rng.uniform(-0.02, 0.02, n),
                          rng.uniform(0.004, 0.036, n)])
    radius = rng.choice([0.002, 0.004], n)
    with h5py.File(path, "w") as f:
        f.attrs.update(schema_version=1, tcd_version="test", scenario="")
        for k in range(frames):
            g = f.create_group(f"frames/{k:06d}")
            g.attrs.update(time=0.1 * k, step=10 * k, stage="shear")
            v = np.zeros((n, 3))
            v[:, 0] = 0.01 * k * x0[:, 2] / 0.04
            g["particles/x"] = x0 + v * 0.1
            g["particles/v"] = v
            g["particles/w"] = np.zeros((n, 3))
            g["particles/radius"] = radius
            g["particles/layer"] = (x0[:, 2] > 0.02).astype(np.int32)
            g["walls/kind"] = np.array([0, 0, 1], np.int32)
            g["walls/point"] = np.array([[0, 0, 0], [0, 0, 0.04], [0, 0, 0]], float)
            g["walls/direction"] = np.array([[0, 0, 1], [0, 0, -1], [0, 0, 1]], float)
            g["walls/radius"] = np.full(3, 0.03)
            g["walls/extent"] = np.array([[0, 0], [0, 0], [0, 0.04]], float)
            g["walls/force"] = np.zeros((3, 3))
            g["bonds/i"] = np.arange(0, n - 1, dtype=np.int32)
            g["bonds/j"] = np.arange(1, n, dtype=np.int32)
            g["bonds/state"] = (np.arange(n - 1) < 5 * k).astype(np.int8)
    return path


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    return write_states(tmp_path_factory.mktemp("states") / "states.h5")


def test_load_frame_reads_the_schema_and_rejects_bad_requests(states, tmp_path):
    assert render.frame_count(states) == 3
    last = render.load_frame(states)
    assert last["step"] == 20 and last["stage"] == "shear" and last["x"].shape == (40, 3)
    assert last["wall_kind"].tolist() == [0, 0, 1] and last["bond_state"].sum() == 10
    assert render.load_frame(states, 0)["time"] == 0.0
    with pytest.raises(ValueError, match=r"states\.h5.*frame 3"):
        render.load_frame(states, 3)
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        render.load_frame(tmp_path / "nope.h5")


def test_a_prepared_sample_renders_as_a_file_of_one_frame(states, tmp_path):
    """`tcd render prepared.h5` said "a tcd 'checkpoint' file, not a states file" (session 42
    audit): a prepared sample or a checkpoint holds one state, which renders as frame 0, the
    same picture as that state written as a frame of a states file."""
    from tcd import io
    frame = {k: v for k, v in h5_frame(states, 2).items()}
    sample = tmp_path / "prepared.h5"
    io.save_checkpoint(sample, frame, {"time": 0.2})
    assert render.frame_count(sample) == 1
    one = render.load_frame(sample)
    want = render.load_frame(states, 2)
    for key in ("x", "radius", "layer", "wall_kind", "wall_point", "bond_state"):
        np.testing.assert_array_equal(one[key], want[key], err_msg=key)
    assert one["time"] == pytest.approx(0.2)
    with pytest.raises(ValueError, match="holds one state: frame 0"):
        render.load_frame(sample, 1)
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    render.render_file(sample, a, width=96, height=72)
    render.render_file(states, b, frame=2, width=96, height=72)
    # the same grains and walls, pixel for pixel below the top line's label (a states frame
    # names its stage there, a prepared sample has none)
    assert np.array_equal(iio.imread(a)[10:], iio.imread(b)[10:])


def test_a_prepared_sample_names_its_layers_by_its_own_courses(states, tmp_path):
    """A sample of the surface course alone was labelled "binder course": a prepared sample
    did not say which course each layer id was (the user audit of session 48). Its meta now
    does, and a run's checkpoint says it through its scenario."""
    from tcd import io
    frame = {k: v for k, v in h5_frame(states, 2).items()}
    frame["particles/layer"] = np.zeros_like(frame["particles/layer"])
    plain = tmp_path / "plain.h5"
    io.save_checkpoint(plain, frame, {"time": 0.2})
    assert [label for label, _ in render.layer_legend(render.load_frame(plain))] == ["binder course"]
    own = tmp_path / "surface_only.h5"
    io.save_checkpoint(own, frame, {"time": 0.2, "courses": ["surface"]})
    assert render.load_frame(own)["courses"] == ("surface",)
    assert [label for label, _ in render.layer_legend(render.load_frame(own))] == ["surface course"]
    ck = tmp_path / "checkpoint.h5"
    io.save_checkpoint(ck, frame, {"time": 0.2, "scenario_text":
                                   '[[stage]]\nkind = "prepare"\ncourses = ["surface", "binder"]\n'})
    assert render.load_frame(ck)["courses"] == ("surface", "binder")


def h5_frame(path, k):
    """Frame k of a states file as the flat dict of arrays it was written from."""
    out = {}
    with h5py.File(path, "r") as f:
        f[f"frames/{k:06d}"].visititems(
            lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_render_file_writes_png_and_gif(states, tmp_path):
    png = tmp_path / "frame.png"
    render.render_file(states, png, color="speed", width=96, height=72)
    img = iio.imread(png)
    assert img.shape[:2] == (72, 96) and img.dtype == np.uint8
    assert (img[:, :, :3] < 250).any(axis=-1).mean() > 0.05, "something was drawn"
    gif = tmp_path / "anim.gif"
    render.render_file(states, gif, frames="all", color="bond-damage", section="xz",
                           width=80, height=60)
    frames = iio.imread(gif, index=None)
    assert frames.shape[:3] == (3, 60, 80)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.gif", "frame.png"]


@pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is not None,
                    reason="imageio-ffmpeg installed: mp4 works")
def test_mp4_without_ffmpeg_says_so(states, tmp_path):
    with pytest.raises(RuntimeError, match=r"imageio-ffmpeg.*\.gif"):
        render.render_file(states, tmp_path / "anim.mp4", frames="all")
    assert not list(tmp_path.iterdir())


def test_failed_write_leaves_previous_file_intact(tmp_path, monkeypatch):
    def crash_midway(path, image, **kw):
        Path(path).write_bytes(b"half an image")
        raise OSError("disk full")

    out = tmp_path / "image.png"
    out.write_bytes(b"old")
    monkeypatch.setattr(iio, "imwrite", crash_midway)
    with pytest.raises(OSError, match="disk full"):
        render.write_image(np.zeros((4, 4, 3), np.uint8), out)
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["image.png"]


def test_layers_take_the_colour_and_name_of_their_course(states, tmp_path):
    """Layer ids are positions in the prepare stage's `courses`: with courses = ["surface",
    "binder"] layer 0 is a surface course. The renderer took 0 as binder, 1 as surface
    whatever the scenario said (session 44's audit)."""
    import h5py
    from tcd.config import PrepareStage
    # a file without its scenario reads as a prepare stage's default courses
    assert render.DEFAULT_COURSES == tuple(PrepareStage.model_fields["courses"].default)
    frame = render.load_frame(states, 0)
    assert frame["courses"] is None                       # its scenario is empty: the default
    assert [label for label, _ in render.layer_legend(frame)] == ["surface course",
                                                                  "binder course"]
    swapped = tmp_path / "swapped.h5"
    import shutil
    shutil.copy(states, swapped)
    with h5py.File(swapped, "a") as f:
        f.attrs["scenario"] = ('name = "s"\n[[stage]]\nkind = "prepare"\n'
                               'courses = ["surface", "binder"]\n')
    frame = render.load_frame(swapped, 0)
    assert frame["courses"] == ("surface", "binder")
    colors, _ = render.particle_colors(frame, "layer")
    dark = colors.mean(axis=1) < 0.5
    np.testing.assert_array_equal(dark, np.asarray(frame["layer"]) == 1)   # layer 1: binder
    labels = [label for label, _ in render.layer_legend(frame)]
    assert labels == ["binder course", "surface course"]                  # top course first
    three = dict(frame, courses=("binder", "binder", "surface"),
                 layer=np.array([0, 1, 2] * (len(frame["layer"]) // 3)
                                + [0] * (len(frame["layer"]) % 3), np.int32))
    assert [label for label, _ in render.layer_legend(three)] == ["surface course",
                                                                  "binder course"]


def test_an_animation_frames_its_camera_as_the_still_image(tmp_path):
    """A perspective GIF with a colour bar was framed for the whole width but drawn in the
    85 % left of the bar: grains cut at the bar's strip, 13 % closer than the still (session
    44's audit). Frame 0 of the GIF now shows the grains where the still does."""
    import h5py
    path = write_states(tmp_path / "wide.h5", frames=2, n=60, seed=3)
    with h5py.File(path, "a") as f:             # grains over x = +-100 mm: framed by the width
        for g in f["frames"].values():
            x = g["particles/x"][...]
            x[:, 0] *= 5.0
            g["particles/x"][...] = x
    still, gif = tmp_path / "still.png", tmp_path / "anim.gif"
    kw = dict(color="speed", camera="perspective", width=300, height=150)
    render.render_file(path, still, frame=0, **kw)
    render.render_file(path, gif, frames=[0, 1], **kw)
    a = iio.imread(still)[:, :, :3]
    b = iio.imread(gif, index=0)[:, :, :3]
    area = render.render_area_width(300, True)
    grains_a = ~background(a[:, :area])
    grains_b = ~background(b[:, :area])
    assert grains_a.sum() > 500
    assert np.mean(grains_a != grains_b) < 0.01


def test_a_render_onto_a_file_keeps_its_mode_and_makes_its_folder(tmp_path):
    """Renders go through io.atomic_path as every other output (session 44: render had its
    own copy, which gave a replaced file the umask's mode and did not fsync)."""
    out = tmp_path / "image.png"
    out.write_bytes(b"old")
    out.chmod(0o640)
    render.write_image(np.full((4, 4, 3), 7, np.uint8), out)
    assert (out.stat().st_mode & 0o777) == 0o640
    assert iio.imread(out)[0, 0, 0] == 7
    deep = tmp_path / "a" / "b" / "image.png"
    render.write_image(np.zeros((4, 4, 3), np.uint8), deep)
    assert [p.name for p in deep.parent.iterdir()] == ["image.png"]


def test_figures_are_written(states, tmp_path):
    render.figure_sample(states, tmp_path / "fig2.png", width=120, height=90)
    assert iio.imread(tmp_path / "fig2.png").shape[:2] == (90, 120)
    render.figure_velocity(states, tmp_path / "fig3.png", [1, 2], panel_width=120)
    fig3 = iio.imread(tmp_path / "fig3.png")
    assert fig3.shape[1] > fig3.shape[0] > 100, "two panels side by side"


def test_fig3_colours_grains_by_their_velocity_over_the_ring_speed(tmp_path, monkeypatch):
    """With a ring moving between the frames, Fig. 3 colours v_x / v_ring on a fixed scale:
    a grain moving with the ring takes the colour of 1, a grain at rest the colour of 0."""
    path = tmp_path / "states.h5"
    n, ring_v = 2, 1e-3
    with h5py.File(path, "w") as f:
        f.attrs.update(schema_version=1, tcd_version="test", scenario="")
        for k, t in enumerate((0.0, 0.5, 1.0)):
            g = f.create_group(f"frames/{k:06d}")
            g.attrs.update(time=t, step=k, stage="shear")
            g["particles/x"] = np.array([[0.0, 0.0, 0.01], [0.0, 0.0, 0.03]])
            v = np.zeros((n, 3))
            v[1, 0] = ring_v * min(k, 1)                 # the upper grain moves with the ring
            g["particles/v"] = v
            g["particles/radius"] = np.full(n, 0.01)
            g["walls/kind"] = np.array([0, 1, 1], np.int32)
            g["walls/point"] = np.array([[0, 0, 0], [0, 0, 0], [ring_v * t, 0, 0.02]], float)
            g["walls/direction"] = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1]], float)
            g["walls/radius"] = np.full(3, 0.02)
            g["walls/extent"] = np.array([[0, 0], [0, 0.02], [0, 0.02]], float)
            g["walls/force"] = np.zeros((3, 3))
    frames = [render.load_frame(path, k) for k in (1, 2)]
    assert render.driving_speed(frames) == pytest.approx(ring_v)
    assert render.driving_speed(frames[:1]) == 0.0
    assert render.ring_offset(frames[1]) == pytest.approx(ring_v * 1.0)
    seen = {}
    real_render = render._render

    def spy(x, radius, colors, **kw):
        seen.setdefault("colors", []).append(np.array(colors))
        return real_render(x, radius, colors, **kw)
    import matplotlib
    cmap = matplotlib.colormaps["viridis"]
    lo, hi = render.VELOCITY_RANGE
    monkeypatch.setattr(render, "_render", spy)
    render.figure_velocity(path, tmp_path / "fig3.png", [1, 2], panel_width=80,
                           velocity="instant")
    for colors in seen["colors"]:
        assert np.allclose(colors[0], cmap((0.0 - lo) / (hi - lo))[:3])    # at rest
        assert np.allclose(colors[1], cmap((1.0 - lo) / (hi - lo))[:3])    # with the ring
    assert iio.imread(tmp_path / "fig3.png").shape[1] > 100


def test_viewer_without_display_points_to_offscreen_render(states, monkeypatch):
    from tcd import viewer
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match=r"display.*Vulkan.*tcd render"):
        viewer.view(states)


@pytest.mark.f64_only   # `python -m tcd.render --regen-reference` renders the reference in f64
def test_regen_reference_writes_to_the_given_place(tmp_path, monkeypatch):
    monkeypatch.setattr(render, "REFERENCE_IMAGE", Path(tmp_path / "ref.png"))
    assert render.main(["--regen-reference"]) == 0
    np.testing.assert_array_equal(iio.imread(tmp_path / "ref.png")[:, :, :3],
                                  render.render_reference())


def test_load_frame_fills_optional_particle_data_and_orders_frames(tmp_path):
    path = tmp_path / "minimal.h5"
    with h5py.File(path, "w") as f:
        for k in (0, 1000000, 999999):          # a 7-digit name sorts after the 6-digit ones
            g = f.create_group(f"frames/{k:06d}")
            g.attrs.update(time=float(k), step=k, stage="pour")
            g["particles/x"] = np.zeros((2, 3))
            g["particles/radius"] = np.full(2, 1e-3)
    last = render.load_frame(path)
    assert last["step"] == 1000000 and last["v"].shape == (2, 3) and not last["v"].any()
    assert last["layer"].tolist() == [0, 0] and last["wall_kind"].shape == (0,)
    assert last["bond_i"].shape == (0,)
    with h5py.File(path, "a") as f:
        del f["frames/000000/particles/radius"]
    with pytest.raises(ValueError, match=r"minimal\.h5: frame 000000.*radius"):
        render.load_frame(path, 0)


# --- session 43's mutation audit of the walls, the API, the benchmarks and the renderer -------
def test_speed_and_vx_colour_values_and_their_default_ranges():
    """speed is |v| of all three components (mm/s), vx the signed x component; the vx scale is
    symmetric about 0 (so that rest is the colormap's middle), the speed scale starts at 0."""
    from tcd import render
    frame = {"v": np.array([[0.0, 0.0, -0.003], [0.003, -0.004, 0.0], [-0.002, 0.0, 0.0]])}
    np.testing.assert_allclose(render.particle_values(frame, "speed"), [3.0, 5.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(render.particle_values(frame, "vx"), [0.0, 3.0, -2.0], rtol=1e-12)
    assert render.default_range("vx", np.array([-2.0, 1.0])) == (-2.0, 2.0)
    assert render.default_range("speed", np.array([1.0, 3.0])) == (0.0, 3.0)


def test_the_perspective_field_of_view_is_vertical():
    """fov_deg is the vertical angle: half height tan(fov/2), half width that times W/H."""
    from tcd.render import Camera
    cam = Camera("perspective", eye=(0.0, -1.0, 0.0), target=(0.0, 0.0, 0.0), fov_deg=90.0)
    half_w, half_h = cam.half_extents(200, 100)
    assert half_h == pytest.approx(1.0, rel=1e-12) and half_w == pytest.approx(2.0, rel=1e-12)
    # a point at 45 degrees above the axis lands on the top edge of the image
    (col, row), = cam.project(np.array([[0.0, 0.0, 1.0]]), 200, 100)[0]
    assert row == pytest.approx(0.0, abs=1e-9) and col == pytest.approx(100.0, abs=1e-9)


def test_a_section_view_frames_only_the_grains_the_cut_leaves():
    """With a cutting plane the preset camera frames the grains on the kept side (centre within
    a radius of it): a grain far on the removed side widens nothing."""
    from tcd import render
    x = np.array([[0.0, 0.01, 0.0], [0.2, -0.05, 0.0]])
    r = np.array([0.005, 0.005])
    plane = (np.zeros(3), np.array([0.0, 1.0, 0.0]))       # keeps y >= 0, looks along +y
    cam = render._resolve_camera("front", x, r, 100, 100, plane)
    assert cam.ortho_width == pytest.approx(1.08 * 0.01, rel=1e-9)
    np.testing.assert_allclose(np.asarray(cam.target)[[0, 2]], [0.0, 0.0], atol=1e-12)
    whole = render._resolve_camera("front", x, r, 100, 100, None)
    assert whole.ortho_width > 10 * cam.ortho_width                # the control: both grains


def _velocity_states(path, v, ring_v):
    """Three frames of grains `v` (N,3) in a mould, a ring moving at ring_v (m/s) along x."""
    import h5py
    n = len(v)
    with h5py.File(path, "w") as f:
        f.attrs.update(schema_version=1, tcd_version="test", scenario="")
        for k, t in enumerate((0.0, 0.5, 1.0)):
            g = f.create_group(f"frames/{k:06d}")
            g.attrs.update(time=t, step=k, stage="shear")
            x = np.zeros((n, 3))
            x[:, 0] = 0.002 * (np.arange(n) % 9) - 0.008
            x[:, 2] = 0.002 + 0.002 * (np.arange(n) // 9)
            g["particles/x"] = x
            g["particles/v"] = np.asarray(v, float)
            g["particles/radius"] = np.full(n, 0.001)
            g["walls/kind"] = np.array([0, 1], np.int32)
            g["walls/point"] = np.array([[0, 0, 0], [ring_v * t, 0, 0.0]], float)
            g["walls/direction"] = np.array([[0, 0, 1], [0, 0, 1]], float)
            g["walls/radius"] = np.full(2, 0.02)
            g["walls/extent"] = np.array([[0, 0], [0, 0.06]], float)
            g["walls/force"] = np.zeros((2, 3))


def test_fig3_colours_signed_vx_and_tops_the_speed_scale_at_the_99th_percentile(tmp_path,
                                                                                  monkeypatch):
    """Fig. 3 colours v_x / v_ring signed (a grain moving against the ring is below rest, at
    the scale's bottom, not mirrored to +1); without a moving ring it colours |v| on a scale
    topped by the 99th percentile of the speeds (one grain falling at 1 m/s among 200 at
    1 mm/s leaves the scale at 1 mm/s)."""
    from tcd import render
    seen = []
    real = render.value_colors

    def spy(values, cmap, lo, hi):
        seen.append((np.array(values), lo, hi))
        return real(values, cmap, lo, hi)
    monkeypatch.setattr(render, "value_colors", spy)
    ring_v = 1e-3
    _velocity_states(tmp_path / "a.h5", [[-ring_v, 0, 0], [ring_v, 0, 0]], ring_v)
    render.figure_velocity(tmp_path / "a.h5", tmp_path / "a.png", [1, 2], panel_width=64,
                           velocity="instant")
    assert seen and all(np.allclose(vals, [-1.0, 1.0]) and (lo, hi) == render.VELOCITY_RANGE
                        for vals, lo, hi in seen)
    seen.clear()
    v = np.zeros((201, 3))
    v[:, 2] = -1e-3
    v[0, 2] = -1.0
    _velocity_states(tmp_path / "b.h5", v, 0.0)
    render.figure_velocity(tmp_path / "b.h5", tmp_path / "b.png", [1, 2], panel_width=64,
                           velocity="instant")
    assert seen and all(lo == 0.0 and hi == pytest.approx(1.0, rel=1e-9) for _, lo, hi in seen)
    np.testing.assert_allclose(seen[0][0][:3], [1000.0, 1.0, 1.0], rtol=1e-9)



def test_fig3_shows_each_grain_s_mean_velocity_between_two_snapshots(tmp_path, monkeypatch):
    """Fig. 3's default, the paper's "average velocity of grains": each grain's displacement
    from its frame to the next of the same stage over their time apart (from the previous one
    for a stage's last frame), whatever velocity the frame holds; a frame with no frame of its
    stage and grains next to it keeps its own velocities."""
    import h5py
    from tcd import render
    seen = []
    real = render.value_colors

    def spy(values, cmap, lo, hi):
        seen.append(np.array(values))
        return real(values, cmap, lo, hi)
    monkeypatch.setattr(render, "value_colors", spy)
    ring_v = 1e-3
    path = tmp_path / "mean.h5"
    # frames at t = 0, 0.5, 1.0 (shear), 1.5 (another stage, other grains); the upper grain goes
    # with the ring from 0.5 s on, the lower one is still; the frames' own velocities are noise
    _velocity_states(path, [[5e-3, 0, -9e-3], [-4e-3, 0, 7e-3]], ring_v)
    with h5py.File(path, "a") as f:
        for k in (1, 2):
            x = f[f"frames/{k:06d}/particles/x"][...]
            x[1, 0] += ring_v * (0.5 * k - 0.5)
            f[f"frames/{k:06d}/particles/x"][...] = x
        g = f.create_group("frames/000003")
        g.attrs.update(time=1.5, step=3, stage="later")
        for key in ("particles/v", "particles/radius", "walls/kind", "walls/point",
                    "walls/direction", "walls/radius", "walls/extent", "walls/force"):
            g[key] = f[f"frames/000002/{key}"][...]
        g["particles/x"] = f["frames/000002/particles/x"][...] + 0.001
    got = {}
    for k in (0, 1, 2):
        frame, span = render.mean_velocity(path, k, render.load_frame(path, k))
        got[k] = (frame["v"], span)
    np.testing.assert_allclose(got[0][0], 0.0, atol=1e-15)               # to frame 1: still
    np.testing.assert_allclose(got[1][0][1], [ring_v, 0, 0], rtol=1e-9)  # to frame 2
    np.testing.assert_allclose(got[1][0][0], 0.0, atol=1e-15)
    np.testing.assert_allclose(got[2][0][1], [ring_v, 0, 0], rtol=1e-9)  # from 1: 3 is "later"
    assert got[1][1] == "to frame 2, ring 1.00 mm" and got[2][1].startswith("from frame 1")
    alone = tmp_path / "alone.h5"
    _velocity_states(alone, [[5e-3, 0, 0]], ring_v)
    with h5py.File(alone, "a") as f:
        for k in (0, 2):
            f[f"frames/{k:06d}"].attrs["stage"] = "prepare"
    frame, span = render.mean_velocity(alone, 1, render.load_frame(alone, 1))
    assert span == "" and np.allclose(frame["v"], [[5e-3, 0, 0]])         # its own
    import matplotlib.axes
    titles = []
    real_title = matplotlib.axes.Axes.set_title
    monkeypatch.setattr(matplotlib.axes.Axes, "set_title",
                        lambda ax, text, *a, **kw: titles.append(text) or real_title(ax, text, *a, **kw))
    render.figure_velocity(path, tmp_path / "fig3.png", [1, 2], panel_width=64)
    assert titles[0].endswith("mean velocity to frame 2, ring 1.00 mm"), titles
    assert titles[1].endswith("mean velocity from frame 1, ring 0.50 mm"), titles
    assert len(seen) == 2
    np.testing.assert_allclose(seen[0], [0.0, 1.0], atol=1e-9)           # v_x / ring
    np.testing.assert_allclose(seen[1], [0.0, 1.0], atol=1e-9)
    with pytest.raises(ValueError, match="velocity 'both': expected one of mean, instant"):
        render.figure_velocity(path, tmp_path / "x.png", [1], velocity="both")


def test_a_damaged_file_is_named_in_the_one_line_error(states, tmp_path, capsys):
    """h5py reports some damage as RuntimeError, which `tcd render` took for its own message
    (a missing MP4 writer) and printed without the file ("tcd: error: Object visitation failed
    (bad object header version number)"; session 72's review). Now, as `tcd info`, `export`
    and `analyse`, every refusal names the file: 512 bytes of 0xff at 19 places in turn."""
    from tcd import cli
    data = states.read_bytes()
    damaged = tmp_path / "damaged.h5"
    refused = []
    for k in range(1, 20):
        at = k * len(data) // 20
        damaged.write_bytes(data[:at] + b"\xff" * 512 + data[at + 512:])
        capsys.readouterr()
        rc = cli.main(["render", str(damaged), "--out", str(tmp_path / "x.png"), "--width",
                       "64", "--height", "48"])
        err = capsys.readouterr().err
        assert rc in (0, 2), (k, rc, err)
        if rc == 2:
            assert err.startswith(f"tcd: error: {damaged}: ") and err.count("\n") == 1, (k, err)
            refused.append(err)
    assert any("RuntimeError" in err for err in refused), refused


def test_a_gif_plays_at_the_frame_rate_asked_or_is_refused(states, tmp_path):
    """A GIF's delays are hundredths of a second: --fps 200 was written as delays of 0 (the
    first frame's missing), which viewers play at about 10 frames per second, slower than
    --fps 50 (session 72's review). Up to 50 the delays are 1/fps; above, refused."""
    from PIL import Image
    for fps, delay in ((10, 100), (50, 20)):
        out = tmp_path / f"a{fps}.gif"
        render.render_file(states, out, frames="all", fps=fps, width=64, height=48)
        delays = []
        with Image.open(out) as im:
            for k in range(im.n_frames):
                im.seek(k)
                delays.append(im.info.get("duration"))
        assert delays == [delay] * 3, (fps, delays)
    with pytest.raises(ValueError, match="at most 50 frames per second in a GIF"):
        render.render_file(states, tmp_path / "b.gif", frames="all", fps=200, width=64, height=48)
    assert not (tmp_path / "b.gif").exists()
