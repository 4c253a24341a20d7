"""Fit the 15 real ping-pong table drops (the table in docs/pages/fitting.md).

Run from the repository root: ``python docs/scripts/realdata_table_fits.py``. Reads the data
from ``../shared/realdata`` (never copied into the repository) and prints one JSON line per
file (e, its standard error and the rms residual in px, fitted on the whole track and after
the first bounce; the pixel scale from gravity; e from flight-time ratios), then the
Markdown table of the docs page and a JSON summary line.

The method is the one of ``notebooks/02_fit_video_tracks.py`` (keep the two in step):
``estim.fit_pixels`` with the defaults of ``estim fit --pixels`` (scale from gravity,
surface row from the bounces, up to 5 restarts), on the whole track and with
``from_bounce=1``; every file padded to 400 samples so that all share one compiled fit.
An after-bounce fit measures e when e is identifiable (a bounce inside its window, a finite
standard error) and its rms residual is at most ``RMS_OK_PX``; every other file is listed
in the table with the reason it is not used.

``--restarts N`` sets the fit's restarts (default 5; 0 shows the minima the restarts
avoid). ``--drag-check`` also runs the same pipeline on simulated drops with quadratic air drag
and a known e (written to a temporary folder): how far the drag-free fit reads e from the
truth at the speeds of these drops.
"""

import json
import pathlib
import re
import sys
import tempfile

import numpy as np

import estim

DATA = pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "realdata"
REAL = DATA / "pingpong_drop_nicofighter45"
TABLE = REAL / "table"
SCENE = pathlib.Path(__file__).resolve().parents[2] / "data" / "scenes" / "drop.xml"
DT = 0.01  # s per frame, as the authors assumed
RMS_OK_PX = 4.0  # "a few pixels" (the same threshold as notebook 02)


def used(row):
    """(True, "") if the after-bounce fit of a file measures e, else (False, why not)."""
    f = row["from_bounce_1"]
    if "e" not in f:
        return False, "no: fewer than 2 bounces"
    if f["bounces"] < 1 or not np.isfinite(f["stderr_e"]):
        return False, "no: no 2nd bounce, e not identifiable"
    if f["rms_px"] > RMS_OK_PX:
        return False, f"no: rms {f['rms_px']:.1f} px > {RMS_OK_PX:g} px"
    return True, "yes"


def mean_sem(x):
    x = np.asarray(x, dtype=float)
    return float(np.mean(x)), float(np.std(x, ddof=1) / np.sqrt(len(x)))


def simulated_drop(path, *, e, drag_coefficient, seed, mpp=137.1e-2 / 911, height=2.4):
    """A vertical drop with quadratic drag ``a = -g - k |v| v``, ``k = rho C_d pi r^2 / 2m``
    (rho 1.2 kg/m^3, the 2.7 g, 2 cm ball), bounces ``v -> -e v`` on the table, written as an
    ``a;b;`` track: 100 fps, the authors' scale, 0.4 px noise, 0.2-0.3 s in the hand first."""
    rng = np.random.default_rng(seed)
    g, k = 9.81, 1.2 * drag_coefficient * np.pi * 0.02**2 / (2 * 2.7e-3)
    h, z, vz, x, vx = 1e-4, height + rng.uniform(-0.1, 0.1), 0.0, 0.0, rng.uniform(-0.05, 0.05)
    t, t_hold, n_frames, frames = 0.0, 0.2 + rng.uniform(0, 0.1), 230 + int(rng.integers(0, 20)), []

    def acc(vx, vz):
        speed = np.hypot(vx, vz)
        return np.array([-k * speed * vx, -g - k * speed * vz])

    while len(frames) < n_frames:
        if t >= len(frames) * DT - 1e-12:
            frames.append((x, z))
        if t >= t_hold:  # RK4 step of (x, z, vx, vz)
            v = np.array([vx, vz])
            a1 = acc(*v)
            a2 = acc(*(v + h / 2 * a1))
            a3 = acc(*(v + h / 2 * a2))
            a4 = acc(*(v + h * a3))
            x, z = np.array([x, z]) + h * (v + h / 6 * (a1 + a2 + a3))
            vx, vz = v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
            if z < 0 and vz < 0:
                z, vz = -z, -e * vz
        t += h
    xz = np.array(frames)
    a = 750 + xz[:, 0] / mpp + rng.normal(0, 0.4, len(xz))
    b = 1830 - xz[:, 1] / mpp + rng.normal(0, 0.4, len(xz))
    path.write_text("".join(f"{p:.3f};{q:.3f};\n" for p, q in zip(a, b, strict=True)))


def drag_check(scene, e=0.87):
    """The drag-free pipeline on simulated drops with known e, without and with drag."""
    with tempfile.TemporaryDirectory() as tmp:
        for cd in (0.0, 0.3):
            for seed in range(3):
                path = pathlib.Path(tmp) / f"drop-{cd}-{seed}.txt"
                simulated_drop(path, e=e, drag_coefficient=cd, seed=seed)
                track = estim.read_pixel_track(path, frame_interval=DT)
                row = {"true_e": e, "drag_coefficient": cd, "seed": seed,
                       "release_over_bounce_scale": scale_ratio(track),
                       "e_flight_times": [round(float(x), 4) for x in estim.restitution_from_flight_times(track).e]}
                for k in (0, 1):
                    res, _, s, _ = estim.fit_pixels(path, scene, ball="pingpong", frame_interval=DT,
                                                    from_bounce=k, pad_to=400)
                    bf = res.balls["pingpong"]
                    row[f"from_bounce_{k}"] = {"e": round(bf.values["e"], 4), "rms_px": round(bf.rms_m / s, 2)}
                print(json.dumps({"drag_check": row}), flush=True)


def scale_ratio(track):
    """Gravity's scale from the fall from the hand over that from bounce-to-bounce flights
    (1 without drag; drag slows the fall, so above 1), or NaN without a complete flight."""
    plain = estim.estimate_pixel_scale(track, DT)
    complete = estim.estimate_pixel_scale(track, DT, complete_only=True)
    first = plain.flights[0]
    if len(complete.flights) == len(plain.flights) or first[0] == complete.flights[0][0]:
        return float("nan")
    return float(first[3] / complete.metres_per_pixel)


def main():
    estim.enable_compilation_cache()
    scene = estim.load_scene(SCENE)
    args = sys.argv[1:]
    if "--drag-check" in args:
        drag_check(scene)
    restarts = int(args[args.index("--restarts") + 1]) if "--restarts" in args else 5
    rows = []
    for i in range(15):
        path = TABLE / f"tracked-{i}.txt"
        row = {"file": i}
        for k in (0, 1):
            try:
                res, _, s, _ = estim.fit_pixels(path, scene, ball="pingpong", frame_interval=DT,
                                                from_bounce=k, pad_to=400, restarts=restarts)
                bf = res.balls["pingpong"]
                row[f"from_bounce_{k}"] = {"e": bf.values["e"], "stderr_e": bf.stderr["e"],
                                           "rms_px": bf.rms_m / s, "noise_px": bf.noise_m / s,
                                           "bounces": bf.n_bounces, "notes": bf.notes}
                row["metres_per_pixel"] = s if k == 0 else row["metres_per_pixel"]
            except ValueError as exc:  # fewer bounces than from_bounce asks for
                row[f"from_bounce_{k}"] = {"error": str(exc)}
        track = estim.read_pixel_track(path, frame_interval=DT)
        row["e_flight_times"] = [float(x) for x in estim.restitution_from_flight_times(track).e]
        row["release_over_bounce_scale"] = scale_ratio(track)
        row["used"] = used(row)[0]
        rows.append(row)
        print(json.dumps(row), flush=True)

    def cell(f):
        if "e" not in f:
            return ["n/a (no 2nd bounce)", ""]
        if not np.isfinite(f["stderr_e"]):
            return ["not identifiable", f"{f['rms_px']:.1f}"]
        return [f"{f['e']:.4f}", f"{f['rms_px']:.1f}"]

    print("\n| file | e, whole track | rms (px) | e, after bounce 1 | rms (px) | used for e | "
          "e from flight-time ratios |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        cells = [str(r["file"]), *cell(r["from_bounce_0"]), *cell(r["from_bounce_1"]), used(r)[1],
                 ", ".join(f"{x:.3f}" for x in r["e_flight_times"])]
        print("| " + " | ".join(cells) + " |")

    txt = (REAL / "upstream_results_rebond.txt").read_text(encoding="utf-8", errors="replace")
    e_authors = float(re.search(r"restitution est de ([0-9.]+)", txt).group(1))
    se_authors = float(re.search(r"incertitude sur la valeur est de ([0-9.]+)", txt).group(1))
    good = [r for r in rows if r["used"]]
    identifiable = [r for r in rows if "e" in r["from_bounce_1"] and np.isfinite(r["from_bounce_1"]["stderr_e"])]
    e_after, sem_after = mean_sem([r["from_bounce_1"]["e"] for r in good])
    e_ident, sem_ident = mean_sem([r["from_bounce_1"]["e"] for r in identifiable])
    e_whole, sem_whole = mean_sem([r["from_bounce_0"]["e"] for r in rows])
    mpp = [r["metres_per_pixel"] for r in rows]
    second = [r["e_flight_times"][1] for r in rows if len(r["e_flight_times"]) > 1]
    third = [r["e_flight_times"][2] for r in rows if len(r["e_flight_times"]) > 2]
    summary = {
        "e_after_bounce_1": e_after, "sem_after_bounce_1": sem_after,
        "sd_after_bounce_1": float(np.std([r["from_bounce_1"]["e"] for r in good], ddof=1)),
        "median_after_bounce_1": float(np.median([r["from_bounce_1"]["e"] for r in good])),
        "files_used": [r["file"] for r in good],
        "e_all_identifiable": e_ident, "sem_all_identifiable": sem_ident,
        "files_identifiable": [r["file"] for r in identifiable],
        "e_whole_track": e_whole, "sem_whole_track": sem_whole,
        "median_whole_track": float(np.median([r["from_bounce_0"]["e"] for r in rows])),
        "rms_px_whole_track": [min(r["from_bounce_0"]["rms_px"] for r in rows),
                               max(r["from_bounce_0"]["rms_px"] for r in rows)],
        "metres_per_pixel": [float(np.mean(mpp)), float(np.std(mpp, ddof=1))],
        "release_over_bounce_scale": mean_sem([r["release_over_bounce_scale"] for r in rows
                                               if np.isfinite(r["release_over_bounce_scale"])]),
        "flight_time_ratio_1": mean_sem([r["e_flight_times"][0] for r in rows]),
        "flight_time_ratio_2": [*mean_sem(second), len(second)],
        "flight_time_ratio_3": [*mean_sem(third), len(third)],
        "e_authors": e_authors, "se_authors": se_authors,
        "difference": e_after - e_authors, "combined_uncertainty": float(np.hypot(sem_after, se_authors)),
    }
    print("\n" + json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
