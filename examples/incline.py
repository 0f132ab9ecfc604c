"""A sphere released on an inclined plane: it rolls, or it slips.

A sphere on a plane tilted by theta, with Coulomb friction mu at the contact, rolls without
slipping when tan(theta) < 7/2 mu, with acceleration a = 5/7 g sin(theta) along the slope and
spin w r = v; otherwise it slips, with a = g (sin(theta) - mu cos(theta)) and w r =
5/2 mu g cos(theta) t. The script releases the sphere, steps it with Contact Dynamics and
prints what it measured against these closed forms.

    python examples/incline.py [--theta 20] [--mu 0.3] [--time 0.1] [--arch cpu|gpu]
"""
from __future__ import annotations

import argparse
import math

import numpy as np

G = 9.81


def run(theta_deg: float = 20.0, mu: float = 0.3, time: float = 0.1, h: float = 2e-4) -> dict:
    """Release a 10 mm sphere on the incline, step for `time` s; measured and expected values.
    tcd.init must have been called."""
    from tcd import walls
    from tcd.simulation import Simulation, SolverSettings

    th = math.radians(theta_deg)
    r = 0.005
    normal = np.array([-math.sin(th), 0.0, math.cos(th)])     # the plane's normal, into the domain
    down = np.array([-math.cos(th), 0.0, -math.sin(th)])      # down the slope
    sim = Simulation([r], [normal * r],                       # resting on the plane
                     walls=[walls.plane((0.0, 0.0, 0.0), tuple(normal), friction=mu)],
                     settings=SolverSettings(time_step=h, alert_ratio=0.2),
                     domain=((-0.05,) * 3, (0.05,) * 3))
    steps = int(round(time / h))
    sim.step(steps)
    t = steps * h
    m = 4.0 / 3.0 * math.pi * r**3 * sim.density
    rolls = math.tan(th) < 3.5 * mu
    a = 5.0 / 7.0 * G * math.sin(th) if rolls else G * (math.sin(th) - mu * math.cos(th))
    spin = 5.0 / 7.0 * G * math.sin(th) * t if rolls else 2.5 * mu * G * math.cos(th) * t
    v = sim.velocities()[0]
    out = {"rolls": rolls, "time": t,
           "speed_down_slope": float(v @ down), "expected_speed": a * t,
           "speed_off_plane": float(v @ normal),
           "spin_times_radius": float(np.linalg.norm(sim.angular_velocities()[0]) * r),
           "expected_spin_times_radius": spin,
           "wall_force": sim.wall_force(0).tolist(),
           # the sphere pushes the plane with its normal load m g cos(theta) and drags it
           # down the slope with the friction that holds it back, m (g sin(theta) - a)
           "expected_wall_force": (-m * G * math.cos(th) * normal
                                   + m * (G * math.sin(th) - a) * down).tolist()}
    sim.close()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--theta", type=float, default=20.0, help="tilt of the plane (degrees)")
    ap.add_argument("--mu", type=float, default=0.3, help="friction between sphere and plane")
    ap.add_argument("--time", type=float, default=0.1, help="simulated time (s)")
    ap.add_argument("--arch", choices=("cpu", "gpu"), default="cpu")
    a = ap.parse_args()
    import tcd
    tcd.init(a.arch, "f64")
    o = run(a.theta, a.mu, a.time)
    print(f"theta = {a.theta} deg, mu = {a.mu}: the sphere {'rolls' if o['rolls'] else 'slips'}")
    print(f"speed down the slope after {o['time']:.3f} s: {o['speed_down_slope']:.6f} m/s "
          f"(closed form {o['expected_speed']:.6f})")
    print(f"spin x radius: {o['spin_times_radius']:.6f} m/s "
          f"(closed form {o['expected_spin_times_radius']:.6f})")
    print(f"speed off the plane: {o['speed_off_plane']:.1e} m/s")
    print("force of the sphere on the plane: "
          + ", ".join(f"{f:.6f}" for f in o["wall_force"]) + " N (closed form "
          + ", ".join(f"{f:.6f}" for f in o["expected_wall_force"]) + ")")


if __name__ == "__main__":
    main()
