"""The servo-controlled top plate of the sample preparation (tcd/protocols.py): it follows its
prescribed motion but backs off while the grains push on it with more than its force limit,
so that it never holds a jammed bed below the bed's height."""
import numpy as np

from tcd import walls
from tcd.protocols import Phase, servo_step
from tcd.simulation import Simulation, SolverSettings

R_CYL = 0.01
H = 2e-4


def sandwich(top_gap: float):
    """Two spheres of 2 mm radius stacked on the bottom of a 10 mm cylinder, a servo plate
    `top_gap` above the upper one, told to descend at 5 mm/s to a target 1 mm inside it: a
    target no rigid bed can reach."""
    r = np.array([0.002, 0.002])
    x = np.array([[0.0, 0.0, 0.002], [0.0, 0.0, 0.006]])
    z0 = 0.008 + top_gap
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R_CYL, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), R_CYL, (0.0, 0.05), name="mould"),
          walls.plane((0, 0, z0), (0, 0, -1), radius=R_CYL, name="top plate")]
    sim = Simulation(r, x, walls=wl, settings=SolverSettings(time_step=H),
                     domain=((-R_CYL, -R_CYL, 0.0), (R_CYL, R_CYL, 0.05)))
    weight = float(2600 * 4 / 3 * np.pi * (r**3).sum() * 9.81)
    v = 0.005
    servo = {"wall": 2, "z": z0, "z0": z0, "target": 0.007, "t0": 0.0, "amplitude": 0.0,
             "frequency": 30.0, "force_limit": 3.0 * weight, "v_mean": -v, "v_max": v}
    return sim, Phase("hold", sim.walls, 400, info={"servo": servo}), weight


def test_servo_plate_backs_off_a_jammed_bed_instead_of_ratcheting_into_it(precision):
    sim, phase, weight = sandwich(top_gap=0.0001)
    servo = phase.info["servo"]
    z, push, overlap, floor = [], [], [], []
    for _ in range(400):
        servo_step(sim, phase)
        sim.step()
        z.append(servo["z"])
        push.append(float(sim.wall_force(2)[2]))
        x, r = sim.positions(), sim.radii()
        plate = sim.walls[2].position(sim.time)[2]
        overlap.append(max(0.0, float((x[:, 2] + r).max() - plate),
                           float(2 * r[0] - (x[1, 2] - x[0, 2]))))
        floor.append(float(r[0] - x[0, 2]))
    z, push, overlap = np.array(z), np.array(push), np.array(overlap)
    quantum = servo["v_max"] * H                  # 1 um: the plate's step
    # A step into the jammed stack is infeasible for rigid grains: it ends at the sweep cap
    # with an impulse that grew with every sweep, and the next step, backing off, starts from
    # it and ends at the cap too, the stack sinking half a step into the floor and coming back.
    # In f64 that two-step cycle is stable. In f32 the rounding of these unconverged steps
    # lets the lower grain sink by about one plate step every 60 steps, until the end-of-step
    # projection holds it at the overlap slop (0.002 x 4 mm = 8 um: measured, 8.0 um from
    # step 200 to 1600; session 40). The bound follows the precision.
    slop = sim.settings.overlap_slop * 2 * sim.r_min    # as the projection computes it
    sink = 0.0 if precision == "f64" else slop
    # it came down to the bed (the gap of 0.1 mm closed) ...
    assert z.min() < 0.008 + quantum
    # ... and then never held it below its height: within one step of the bed's top
    assert z[-100:].min() >= 0.008 - sink - 2 * quantum
    # the floor contact holds: the stack sinks by the first infeasible step and half of the
    # next (1.5 um in f64), or to the slop in f32
    assert max(floor) <= sink + 2 * quantum
    # no overlap builds up (the ratcheting plate of session 15 pushed ever deeper)
    assert overlap[-100:].max() <= 3 * quantum
    # no locked-in force: the plate hovers, one step into the bed (a spike of push: rigid
    # grains against a kinematic plate), one step back (the push drops to the weight)
    assert np.mean(push[-100:] <= servo["force_limit"]) >= 0.4
    # the limit matters: the plate did push harder than the weight at times
    assert push.max() > weight


def test_servo_plate_follows_its_motion_while_the_push_is_below_the_limit():
    sim, phase, _ = sandwich(top_gap=0.003)           # 3 mm of free travel
    servo = phase.info["servo"]
    for k in range(100):                              # 100 steps x 1 um: not yet at the bed
        servo_step(sim, phase)
        sim.step()
        assert abs(servo["z"] - (0.011 - (k + 1) * servo["v_max"] * H)) < 1e-12
