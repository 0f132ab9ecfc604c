"""`tcd run NEW.toml --from RUN`: a new run that goes on from another run's checkpoints
(tcd/branch.py): unchanged it gives the uninterrupted run's numbers bit for bit, a longer shear
of a finished run gives the longer run's, another time step ends the phase where it ended,
RUN is only read, and what it may not change is refused before anything is written."""
import hashlib
import json
import os

import numpy as np
import pytest

from conftest import run_tcd
from tcd import backend, io
from test_runner import MICRO, _interrupt_after, _shear_only, load_here, lock_held_elsewhere


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    """The micro sample of test_runner, prepared once (its shear stage dropped)."""
    d = tmp_path_factory.mktemp("branch")
    text = MICRO[:MICRO.index('[[stage]]\nkind = "shear"')]
    (d / "prep.toml").write_text(text)
    assert run_tcd(["run", str(d / "prep.toml"), "--out", str(d / "prep")]) == 0
    return d / "prep" / "sample_3" / "prepared.h5"


@pytest.fixture(scope="module")
def shear(prepared, tmp_path_factory):
    """(scenario path, finished run) of the shear of that sample to 0.2 mm."""
    d = tmp_path_factory.mktemp("shear")
    path = d / "shear.toml"
    path.write_text(_shear_only(prepared.as_posix()))
    assert run_tcd(["run", str(path), "--out", str(d / "whole")]) == 0
    return path, d / "whole"


def _digests(run):
    return {p.relative_to(run): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(run.rglob("*")) if p.is_file() and p.name != ".tcd.lock"}


def _interrupted(scenario, out, monkeypatch, checks=15):
    """`scenario` run into `out` and stopped as by a Ctrl-C after `checks` checks."""
    from tcd import runner
    monkeypatch.setattr(runner, "DeferredInterrupt", _interrupt_after(checks))
    with pytest.raises(KeyboardInterrupt):
        runner.run_scenario(load_here(scenario), out, progress=False)
    monkeypatch.undo()
    _, meta = io.load_checkpoint(out / "sample_3" / "checkpoint.h5")
    return meta


def _series(run):
    return io.read_series(run / "sample_3" / "shear_series.h5")


def test_going_on_unchanged_gives_the_uninterrupted_run_and_leaves_the_source_as_it_was(
        shear, tmp_path, monkeypatch, capsys):
    scenario, whole = shear
    cut = tmp_path / "cut"
    meta = _interrupted(scenario, cut, monkeypatch)
    assert 0 < meta["step_in_phase"] < meta["phase"]["steps"]
    before = _digests(cut)
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--from", str(cut), "--out", str(tmp_path / "new")]) == 0
    report = capsys.readouterr()
    assert _digests(cut) == before                          # the source is only read
    one, two = _series(whole), _series(tmp_path / "new")
    assert set(one) == set(two)
    for key in one:
        assert np.array_equal(one[key], two[key]), key
    a = json.loads((whole / "sample_3" / "summary.json").read_text())
    b = json.loads((tmp_path / "new" / "sample_3" / "summary.json").read_text())
    for key in ("tau_peak_MPa", "d_peak_mm", "bonds_total", "bonds_broken"):
        assert a[key] == b[key], key
    [record] = b["branched_from"]
    assert record["run"] == str(cut.resolve())
    assert record["step"] == meta["step"] and record["time"] == meta["time"]
    assert record["changes"] == [] and record["phase"] == "shear"
    moved = (meta["time"] - meta["phase"]["info"]["t0"]) * 600.0 / 60.0       # mm
    assert record["displacement_mm"] == pytest.approx(moved, rel=1e-12) and moved > 0
    # `tcd run --from` reports where each sample goes on from
    assert (f"seed 3: from {cut.resolve()} at t = {meta['time']:.4f} s (step {meta['step']}, "
            f"stage 1, phase shear), the ring at {moved:.4g} mm, 0 setting(s) changed"
            in report.out + report.err), report
    from tcd import compare, runner
    info = runner.run_info(tmp_path / "new")
    assert ("sample_3: done: 80 grains" in info
            and f"went on from {cut.resolve()} at t = {meta['time']:.4f} s, the ring at "
                f"{moved:.4g} mm (0 setting(s) changed)" in info), info
    # `tcd compare` says where a run went on from another
    compare.compare_runs([whole, tmp_path / "new"], tmp_path / "cmp", labels=["whole", "new"])
    text = (tmp_path / "cmp" / "compare.md").read_text()
    assert (f"went on from another run's state (`tcd run --from`; up to there their curves are "
            f"that run's): new (seed 3) from {cut.resolve()} at t = {meta['time']:.4f} s, "
            f"the ring at {moved:.4g} mm.") in text, text
    # the new run's frames: the source's up to the checkpoint, then its own, as uninterrupted
    assert io.frame_count(tmp_path / "new" / "sample_3" / "states.h5") == \
        io.frame_count(whole / "sample_3" / "states.h5")


def test_a_finished_shear_goes_on_to_a_larger_displacement_as_the_longer_run(shear, tmp_path):
    scenario, whole = shear
    longer = tmp_path / "longer.toml"
    longer.write_text(scenario.read_text().replace("displacement_mm = 0.2", "displacement_mm = 0.3"))
    assert run_tcd(["run", str(longer), "--out", str(tmp_path / "direct")]) == 0
    assert run_tcd(["run", str(longer), "--from", str(whole), "--out", str(tmp_path / "on")]) == 0
    one, two = _series(tmp_path / "direct"), _series(tmp_path / "on")
    assert len(two["time"]) > len(_series(whole)["time"])
    for key in one:
        assert np.array_equal(one[key], two[key]), key
    a = json.loads((tmp_path / "direct" / "sample_3" / "summary.json").read_text())
    b = json.loads((tmp_path / "on" / "sample_3" / "summary.json").read_text())
    for key in ("tau_peak_MPa", "d_peak_mm", "residual_MPa", "bonds_broken"):
        assert a[key] == b[key], key
    assert b["stages"]["0:shear"]["steps"] == a["stages"]["0:shear"]["steps"] == len(one["time"])
    assert b["branched_from"][0]["changes"] == ["stage[1].displacement_mm: 0.2 -> 0.3"]
    # the CSV too holds the whole series, its columns in their order
    head = (tmp_path / "on" / "sample_3" / "shear_series.csv").read_text().splitlines()
    assert head[0] == (tmp_path / "direct" / "sample_3" / "shear_series.csv").read_text() \
        .splitlines()[0] and len(head) == len(one["time"]) + 1


def test_another_time_step_and_tolerance_end_the_shear_where_it_was_to_end(shear, tmp_path,
                                                                            monkeypatch):
    scenario, whole = shear
    cut = tmp_path / "cut"
    meta = _interrupted(scenario, cut, monkeypatch)
    n = meta["step_in_phase"]
    # in another folder, its sample's path written relative to it
    (tmp_path / "elsewhere").mkdir()
    finer = tmp_path / "elsewhere" / "finer.toml"
    text = scenario.read_text()
    sample = text.split('sample = "', 1)[1].split('"', 1)[0]
    rel = os.path.relpath(sample, finer.parent)
    finer.write_text(text.replace("time_step = 5e-4", "time_step = 2.5e-4\ntolerance = 2e-5")
                     .replace(sample, rel))
    # as if RUN had run in the other precision: the change is recorded
    other = "f32" if backend.precision() == "f64" else "f64"
    started = json.loads((cut / "run.json").read_text())
    (cut / "run.json").write_text(json.dumps({**started, "precision": other}))
    # the warm start of the first step at H / 2 is the same forces: the impulses (forces
    # times H) halved; they were kept, and on a shear near its peak (tiny.toml at 0.4 mm)
    # that step then ran to the sweep cap and broke 21 bonds, against 7 halved and none at
    # the same H (session 72's review)
    from tcd.branch import IMPULSE_KEYS, branch_run
    branch_run(load_here(finer), cut, tmp_path / "planned")
    was = io.load_checkpoint(cut / "sample_3" / "checkpoint.h5")[0]
    now = io.load_checkpoint(tmp_path / "planned" / "sample_3" / "checkpoint.h5")[0]
    assert {"contacts/impulse", "bonds/impulse", "bonds/impulse_prev"} <= set(IMPULSE_KEYS)
    for key in set(was) | set(now):
        if key in IMPULSE_KEYS:
            assert np.any(was[key] != 0.0), key
            assert np.allclose(now[key], 0.5 * was[key], rtol=1e-12, atol=0.0), key
        elif not key.startswith("series/"):
            assert np.array_equal(now[key], was[key], equal_nan=was[key].dtype.kind == "f"), key
    assert run_tcd(["run", str(finer), "--from", str(cut), "--out", str(tmp_path / "new")]) == 0
    cut_series, got = io.load_checkpoint(cut / "sample_3" / "checkpoint.h5")[0], _series(tmp_path / "new")
    for key in got:                 # the source's steps, then the new ones
        assert np.array_equal(got[key][:n], cut_series["series/" + key]), key
    whole_s = _series(whole)
    m = len(whole_s["time"])
    assert len(got["time"]) == n + 2 * (m - n)
    v = 600.0 / 60.0 * 1e-3                                  # the ring's speed (m/s)
    assert np.allclose(np.diff(got["displacement"][n - 1:]), v * 2.5e-4, rtol=1e-9)
    assert got["displacement"][-1] == pytest.approx(whole_s["displacement"][-1], rel=1e-9)
    assert got["time"][-1] == pytest.approx(whole_s["time"][-1], abs=1e-9)
    # the new tolerance from the branch on (a step at the 500-sweep cap stops above it)
    capped = got["sweeps"] >= 500
    assert np.all((got["residual"][n:] <= 2e-5) | capped[n:])
    assert np.any(got["residual"][:n][~capped[:n]] > 2e-5)
    b = json.loads((tmp_path / "new" / "sample_3" / "summary.json").read_text())
    assert b["phases"][-1]["steps"] == b["stages"]["0:shear"]["steps"] == len(got["time"])
    assert b["branched_from"][0]["changes"] == [
        f"backend.precision: {other!r} -> {backend.precision()!r}",
        "solver.time_step: 0.0005 -> 0.00025", "solver.tolerance: 0.0001 -> 2e-05",
        f"stage[1].sample: {sample!r} -> {rel!r}"]


def test_the_frames_a_branch_inherits_keep_their_time_step(shear, tmp_path, monkeypatch):
    """A branch at another time step: the frames RUN wrote keep theirs, so `tcd analyse` and
    `tcd export` read their forces as RUN's (they were scaled by H_old / H_new: session 72's
    review), and the new frames' at the new step."""
    from tcd import analysis, export
    scenario, _ = shear
    often = tmp_path / "often.toml"
    often.write_text(scenario.read_text().replace("snapshot_every = 0.05", "snapshot_every = 0.002"))
    cut = tmp_path / "cut"
    _interrupted(often, cut, monkeypatch)
    finer = tmp_path / "finer.toml"
    finer.write_text(often.read_text().replace("time_step = 5e-4", "time_step = 2.5e-4"))
    assert run_tcd(["run", str(finer), "--from", str(cut), "--out", str(tmp_path / "new")]) == 0
    frames = io.frame_count(cut / "sample_3" / "states.h5")
    old = io.read_series(analysis.analyse(cut / "sample_3" / "states.h5", tmp_path / "a")[0])
    new = io.read_series(analysis.analyse(tmp_path / "new" / "sample_3" / "states.h5",
                                          tmp_path / "b")[0])
    assert frames >= 3 and len(new["frame"]) > frames
    for key in ("stress_zz", "normal_force_max"):
        assert np.any(old[key] != 0), key
        assert np.array_equal(new[key][:frames], old[key]), key
    states, h = export.load_states(tmp_path / "new" / "sample_3" / "states.h5")
    assert h is None
    assert [s["time_step"] for s in states] == [5e-4] * frames + [2.5e-4] * (len(states) - frames)
    # a branch of the branch, back at the first step, keeps the record of each frame
    import h5py
    from tcd.branch import _time_steps_after
    with h5py.File(tmp_path / "new" / "sample_3" / "states.h5", "r") as f:
        n = len(states)
        assert _time_steps_after(f, {"frames": n - 1}, 5e-4) == [
            [0, 5e-4], [frames, 2.5e-4], [n - 1, 5e-4]]
        assert _time_steps_after(f, {"frames": n}, 2.5e-4) == [[0, 5e-4], [frames, 2.5e-4]]
    with h5py.File(cut / "sample_3" / "states.h5", "r") as f:
        assert _time_steps_after(f, {"frames": frames}, 5e-4) is None


def test_the_steps_at_the_sweep_cap_count_each_step_against_its_own_cap(shear, tmp_path,
                                                                         monkeypatch):
    """A branch under another max_sweeps: the summary's steps_at_sweep_cap counted the steps
    RUN took against the new cap (all 120 of them at a cap of 5, for 8 at RUN's 1000: session
    72's review). Each step now counts against the cap it ran under."""
    scenario, _ = shear
    cut = tmp_path / "cut"
    meta = _interrupted(scenario, cut, monkeypatch)
    n = meta["step_in_phase"]
    capped = tmp_path / "capped.toml"
    assert "max_sweeps = 500" in scenario.read_text()
    capped.write_text(scenario.read_text().replace("max_sweeps = 500", "max_sweeps = 3", 1)
                      .replace("snapshot_every = 0.05", "snapshot_every = 0.002"))
    assert run_tcd(["run", str(capped), "--from", str(cut), "--out", str(tmp_path / "new")]) == 0
    sweeps = _series(tmp_path / "new")["sweeps"]
    summary = json.loads((tmp_path / "new" / "sample_3" / "summary.json").read_text())
    old_cap = 500
    assert np.count_nonzero(sweeps[:n] >= 3) > 0             # the mistake would show
    expected = int(np.count_nonzero(sweeps[:n] >= old_cap) + np.count_nonzero(sweeps[n:] >= 3))
    assert summary["stages"]["0:shear"]["steps_at_sweep_cap"] == expected
    assert summary["sweep_caps"] == {"0": [[0, old_cap], [n, 3]]}
    # and the snapshots go on at the new schedule from the branch on (the first came at the
    # old one's due time: session 72's review)
    import h5py
    from tcd.runner import next_snapshot_after
    with h5py.File(tmp_path / "new" / "sample_3" / "states.h5", "r") as f:
        times = [float(f["frames"][k].attrs["time"]) for k in sorted(f["frames"], key=int)]
    later = [x for x in times if x > meta["time"] + 1e-12]
    assert later and later[0] == pytest.approx(next_snapshot_after(meta["time"], 0.002), abs=1e-9)


def test_what_a_branch_may_not_do_is_refused_before_anything_is_written(shear, tmp_path,
                                                                        monkeypatch, capsys):
    scenario, whole = shear
    text = scenario.read_text()
    cut = tmp_path / "cut"
    _interrupted(scenario, cut, monkeypatch)
    cases = {
        "material": (text.replace("[solver]", "[material]\nfriction = 0.5\n[solver]"), cut,
                     "material.friction: 0.7 -> 0.5"),
        "ring speed": (text.replace("velocity_mm_per_min = 600.0", "velocity_mm_per_min = 300.0"),
                       cut, "stage[1].velocity_mm_per_min"),
        "behind": (text.replace("displacement_mm = 0.2", "displacement_mm = 0.03"), cut,
                   "past the displacement_mm 0.03 asked"),
        "finished": (text, whole, "that run finished"),
        "seed": (text.replace("seeds = [3]", "seeds = [3, 4]"), cut, "no checkpoint of seed 4"),
        "not a run": (text, tmp_path / "nowhere", "not a run directory"),
        "batched": (text, tmp_path / "batched", "a batched run (--batch)"),
    }
    (tmp_path / "batched").mkdir()
    (tmp_path / "batched" / "batch_checkpoint.h5").write_bytes(b"")
    for name, (body, source, message) in cases.items():
        path = tmp_path / f"{name.replace(' ', '_')}.toml"
        path.write_text(body)
        out = tmp_path / f"out_{name.replace(' ', '_')}"
        assert run_tcd(["run", str(path), "--from", str(source), "--out", str(out)]) != 0, name
        err = capsys.readouterr().err
        assert message in err, (name, err)
        assert not out.exists(), name                       # nothing written
    # a new run's folder only: not one that holds anything, nor the source itself
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    for out, message in ((busy, "exists and is not empty"), (cut, "must be a new directory")):
        assert run_tcd(["run", str(scenario), "--from", str(cut), "--out", str(out)]) != 0
        assert message in capsys.readouterr().err
    assert (busy / "notes.txt").read_text() == "mine"
    assert run_tcd(["run", str(scenario), "--from", str(cut), "--out", str(tmp_path / "x"),
                    "--resume"]) != 0
    assert "--from starts a new run" in capsys.readouterr().err
    # not from a run that a process writes into now
    with lock_held_elsewhere(cut / "sample_3" / ".tcd.lock", "pid 4242 on elsewhere"):
        assert run_tcd(["run", str(scenario), "--from", str(cut), "--out",
                        str(tmp_path / "y")]) != 0
    err = capsys.readouterr().err
    assert "a tcd run writes into it now (" in err and "pid 4242 on elsewhere" in err, err
    assert not (tmp_path / "y").exists()
    # nor on a backend that is not here: refused before the new run's folder is written (it
    # was left behind, with a checkpoint and run.json, and a second try refused for it:
    # session 72's review)
    from tcd import backend as tcd_backend

    def no_gpu(arch):
        if arch == "gpu":
            raise tcd_backend.BackendUnavailable("arch 'gpu' requested but Taichi found no GPU")
    monkeypatch.setattr(tcd_backend, "check_available", no_gpu)
    assert run_tcd(["run", str(scenario), "--from", str(cut), "--out", str(tmp_path / "z"),
                    "--arch", "gpu"]) == 2
    assert "found no GPU" in capsys.readouterr().err
    assert not (tmp_path / "z").exists()
    # a copy that fails half way (here the checkpoint's write) leaves no half a run behind
    from tcd import branch
    monkeypatch.setattr(branch.io, "save_checkpoint", lambda *a, **k: (_ for _ in ()).throw(
        OSError(28, "No space left on device")))
    before = _digests(cut)
    assert run_tcd(["run", str(scenario), "--from", str(cut), "--out", str(tmp_path / "z")]) != 0
    assert "No space left on device" in capsys.readouterr().err
    assert not (tmp_path / "z").exists() and _digests(cut) == before


@pytest.mark.parametrize("name", ["checkpoint.h5", "states.h5"])
def test_a_branch_from_a_damaged_file_is_refused_naming_it(shear, tmp_path, monkeypatch, capsys,
                                                           name):
    """--from a run whose checkpoint was damaged stopped with a traceback (RuntimeError from
    h5py); from one whose states.h5 was damaged, the branch copied it and the new run then
    refused its own copy, leaving that folder behind (session 71). Now the source's files are
    read whole first: one line naming the damaged file, nothing written."""
    import shutil
    from test_runner import _damage
    scenario, _ = shear
    cut = tmp_path / "cut"
    _interrupted(scenario, cut, monkeypatch)
    source = tmp_path / "damaged"
    shutil.copytree(cut, source)
    _damage(source / "sample_3" / name)
    out = tmp_path / "out"
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--from", str(source), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: --from {source}: {source / 'sample_3' / name}: "), err
    assert "damaged: a run cannot go on from it" in err and err.count("\n") == 1, err
    assert not out.exists()
    # the undamaged one goes on
    assert run_tcd(["run", str(scenario), "--from", str(cut), "--out", str(tmp_path / "ok")]) == 0
