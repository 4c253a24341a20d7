"""What summing the friction law's bounce series saves: steps and time per forward call.

Run from the repository root: ``python docs/scripts/friction_series.py`` (about two
minutes). A ping-pong ball (r 0.02 m, thin shell) dropped from 0.3 m onto the table of
``data/scenes/drop.xml`` in a vacuum, with spin (5, 20, 30) rad/s and (0.05, -0.05) m/s
across the table, simulated for 3 s under the friction law (e 0.8; mu 0.01, whose series
slides for three bounces and then grips, and 0.006, whose series slides to its end): the
ODE path's steps and the time of one compiled forward call (the final position),
summed (``FrictionLaw``, the series in closed form) against the same law bounce by
bounce (the law wrapped so that it has no closed-form series), in one process, in
alternating rounds, the median of each. Prints a Markdown table.
"""

from __future__ import annotations

import pathlib
import time

import jax
import numpy as np

import estim
from estim.forward._constants import STEP_UNUSED
from estim.forward.laws import AbstractContactLaw, FrictionLaw

ROOT = pathlib.Path(__file__).resolve().parents[2]
DROP = ROOT / "data" / "scenes" / "drop.xml"
T_END = 3.0
ROUNDS, CALLS = 7, 50


class BounceByBounce(AbstractContactLaw):
    """The friction law without its series' closed form: one step per flight."""

    @property
    def couples_spin(self):
        return True

    def coefficients(self, params):
        return FrictionLaw().coefficients(params)

    def reset(self, v, n, c):
        return FrictionLaw().reset(v, n, c)

    def rebound(self, v, n, c):
        return FrictionLaw().rebound(v, n, c)

    def settle(self, tangential, c):
        return FrictionLaw().settle(tangential, c)

    def impact(self, v, w, n, c):
        return FrictionLaw().impact(v, w, n, c)

    def settle_spin(self, tangential, w, n, c):
        return FrictionLaw().settle_spin(tangential, w, n, c)


def main():
    drop = estim.load_scene(DROP)
    print("| mu | steps summed | steps bounce by bounce | forward summed (ms) | bounce by bounce (ms) |")
    print("|---|---|---|---|---|")
    for mu in (0.01, 0.006):
        params = estim.Params(0.8, 1.0, 0.02, (0.0, 0.0, 0.3), (0.05, -0.05, 0.0), spin=(5.0, 20.0, 30.0),
                              mu=mu, inertia=2.0 / 3.0)
        scenes = (drop.with_law("friction"), drop.with_law(BounceByBounce()))
        steps = [int(np.sum(np.asarray(estim.simulate(s, params, T_END).solution.steps.kind) != STEP_UNUSED))
                 for s in scenes]
        calls = [jax.jit(lambda p, s=s: estim.simulate(s, p, T_END, keep=()).final.position) for s in scenes]
        for f in calls:
            f(params).block_until_ready()
        times = [[], []]
        for _ in range(ROUNDS):
            for k, f in enumerate(calls):
                start = time.perf_counter()
                for _ in range(CALLS):
                    f(params).block_until_ready()
                times[k].append((time.perf_counter() - start) / CALLS * 1e3)
        summed, stepped = (float(np.median(t)) for t in times)
        print(f"| {mu} | {steps[0]} | {steps[1]} | {summed:.3f} | {stepped:.3f} |")


if __name__ == "__main__":
    main()
