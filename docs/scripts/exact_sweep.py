"""The fit sweep on the staircase with exact edges (docs/pages/fitting.md).

Run from the repository root: ``python docs/scripts/exact_sweep.py 0 50`` (seeds 0 to 49,
about two minutes on 2 cores). Truths as ``tests/test_fit.py`` draws them, but with edge
contacts (and rolls over edges) allowed; synthetic tracks with that file's noise, dropped rows and outliers; one
``estim.fit`` per seed on ``data/scenes/stairs_exact.xml``. Prints one line per ball (seed,
ball, contacts on edges, converged, at the noise floor, e - truth, rms in mm) and a summary.
"""

from __future__ import annotations

import pathlib
import sys
import time

import numpy as np

import estim
from estim.forward._trajectory import REST

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
import test_fit as T  # noqa: E402  (the sweep's generator and data, shared with the tests)


def draw(scene, seed):
    """Truth for ``seed``: bocce goes Zeno. Returns it."""
    rng = np.random.default_rng(seed)
    for _ in range(100):
        truth = T.random_truth(rng)
        events = {b: T._events(scene, b, truth[b]) for b in T.BALLS}
        if any(kind == REST for (_, _, kind) in events["bocce"]):
            return truth
    raise RuntimeError(f"no admissible truth for seed {seed}")


def main(first: int, last: int) -> None:
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs_exact.xml")
    n = floor = close = with_edges = floor_edges = 0
    t0 = time.time()
    for seed in range(first, last):
        truth = draw(scene, seed)
        result = estim.fit(scene, T._data(scene, truth, seed, T.NOISES[seed % 3]))
        for b in T.BALLS:
            bf = result.balls[b]
            edges = sum(len(label[1]) > 2 for (_, label, _) in T._events(scene, b, truth[b]))
            n += 1
            floor += bool(bf.at_noise_floor)
            close += abs(bf.values["e"] - truth[b]["e"]) < 0.01
            with_edges += edges > 0
            floor_edges += edges > 0 and bool(bf.at_noise_floor)
            print(seed, b, edges, bf.converged, bf.at_noise_floor, round(bf.values["e"] - truth[b]["e"], 5),
                  round(bf.rms_m * 1e3, 3), flush=True)
    print(f"fits {n}: at the noise floor {floor}, e within 0.01: {close}; balls with edge contacts "
          f"{with_edges}, of them at the floor {floor_edges}; {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]))
