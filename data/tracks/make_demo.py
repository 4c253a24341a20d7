"""Write the demo tracks: data/tracks/stairs_demo.csv and stairs_demo_truth.json.

Run from anywhere:  python data/tracks/make_demo.py

The three balls of the seed stairs scene, released at the seed release point, with known
parameters that differ from the seed defaults, simulated exactly by estim.simulate at 60
frames per second over 2.3 s and degraded like a real tracker (estim's synthesize_tracks):
2 mm Gaussian noise per coordinate, 5 % of frames dropped, 3 gross outliers (5 cm) per
ball, ~1 % of coordinates lost (empty fields). x and z only (a side camera). The script
checks that no ball touches a tread-edge bevel (every impact is on a face with one axis)
and that every ball bounces several times. The parameters were chosen inside regions
where e +- 0.005 and vx0 +- 0.01 touch no bevel either, so small fitting steps around the
truth do not change which faces are hit.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import estim
from estim.tracks._csv import write_tracks_csv
from estim.tracks._synthetic import synthesize_tracks

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
SCENE = ROOT / "data" / "scenes" / "stairs.xml"
TRUTH = {
    "bocce": {"e": 0.58, "mu_t": 0.95, "vx0": 1.175},
    "golf": {"e": 0.725, "mu_t": 0.97, "vx0": 1.275},
    "pingpong": {"e": 0.805, "mu_t": 0.93, "vx0": 1.26},
}
SETTINGS = {
    "t_end": 2.3,
    "frame_rate": 60.0,
    "noise": 0.002,
    "drop_fraction": 0.05,
    "n_outliers": 3,
    "outlier_size": 0.05,
    "lost_fraction": 0.01,
    "with_y": False,
    "seed": 2026,
}
DIGITS = 6  # positions written to the micrometre (noise is 2 mm)


def check_bounces(scene, tracks_details) -> dict:
    """Impacts of every ball (faces, times); raise if one hits an edge bevel or bounces < 3."""
    import jax.numpy as jnp

    balls = list(TRUTH)
    pos = np.stack([tracks_details.release[b][0] for b in balls])
    vel = np.stack([tracks_details.release[b][1] for b in balls])
    p = estim.Params([TRUTH[b]["e"] for b in balls], [TRUTH[b]["mu_t"] for b in balls],
                     [scene.ball(b).radius for b in balls], pos, vel)
    traj = estim.simulate(scene, p, SETTINGS["t_end"], ts=jnp.linspace(0, SETTINGS["t_end"], 8))
    out = {}
    for i, b in enumerate(balls):
        c = int(traj.events.count[i])
        faces = [scene.face_label(int(f)) for f in traj.events.face[i, :c]]
        kinds = [int(k) for k in traj.events.kind[i, :c]]
        bevel = [f for f in faces if len(f[1]) > 2]
        if bevel:
            raise SystemExit(f"{b}: touches tread-edge bevels {bevel}; change its parameters")
        n_impacts = sum(1 for k in kinds if k == 0)
        if n_impacts < 3:
            raise SystemExit(f"{b}: only {n_impacts} impacts; change its parameters")
        out[b] = {
            "impacts": n_impacts,
            "faces": [f"{s}{lab}" for s, lab in faces],
            "first_impact_times": [round(float(t), 4) for t in traj.events.t[i, :min(c, 8)]],
        }
    return out


def main() -> None:
    scene = estim.load_scene(SCENE)
    tracks, details = synthesize_tracks(scene, TRUTH, return_details=True, **SETTINGS)
    bounces = check_bounces(scene, details)
    csv_path = HERE / "stairs_demo.csv"
    write_tracks_csv(csv_path, tracks, digits=DIGITS)
    truth = {
        "scene": "data/scenes/stairs.xml",
        "csv": "data/tracks/stairs_demo.csv",
        "generator": "estim.tracks._synthetic.synthesize_tracks (data/tracks/make_demo.py)",
        "units": {"t": "s", "position": "m", "velocity": "m/s"},
        "balls": {
            b: {
                **TRUTH[b],
                "release_position": details.release[b][0].tolist(),
                "release_velocity": details.release[b][1].tolist(),
                "radius": scene.ball(b).radius,
                "rows": int(tracks.t[b].size),
                "outlier_times": tracks.t[b][details.outlier[b]].tolist(),
                **bounces[b],
            }
            for b in TRUTH
        },
        "settings": {**SETTINGS, "csv_position_decimals": DIGITS},
    }
    (HERE / "stairs_demo_truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    print(f"wrote {csv_path} ({sum(tracks.t[b].size for b in tracks.balls)} rows)")
    for b in TRUTH:
        print(f"  {b}: {bounces[b]['impacts']} impacts on {bounces[b]['faces']}")


if __name__ == "__main__":
    main()
