"""Fit the 15 real ping-pong table drops (the table in docs/pages/fitting.md).

Run from the repository root: ``python docs/scripts/realdata_table_fits.py``. Reads the data
from ``../shared/realdata`` (never copied into the repository) and prints one JSON line per
file: e and rms (px) fitted on the whole track and after the first bounce, the pixel scale
from gravity, and e from flight-time ratios.
"""

import json
import pathlib

import estim
from estim._job import fit_pixels
from estim._tracks import read_pixel_track, restitution_from_flight_times

DATA = pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "realdata"
TABLE = DATA / "pingpong_drop_nicofighter45" / "table"


def main():
    estim.enable_compilation_cache()
    for i in range(15):
        path = TABLE / f"tracked-{i}.txt"
        row = {"file": i}
        for k in (0, 1):
            try:
                # pad_to: all files share one compiled fit
                res, _, s, _ = fit_pixels(path, "data/scenes/drop.xml", ball="pingpong",
                                          frame_interval=0.01, restarts=0, from_bounce=k,
                                          pad_to=400)
                bf = res.balls["pingpong"]
                row[f"from_bounce_{k}"] = {"e": bf.values["e"], "stderr_e": bf.stderr["e"],
                                           "rms_px": bf.rms_m / s, "notes": bf.notes}
                row["metres_per_pixel"] = s
            except ValueError as exc:
                row[f"from_bounce_{k}"] = {"error": str(exc)}
        ft = restitution_from_flight_times(read_pixel_track(path, frame_interval=0.01))
        row["e_flight_times"] = [float(x) for x in ft.e]
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
