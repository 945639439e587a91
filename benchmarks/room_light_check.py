"""Known lights in a lit room: a rendered sphere under 12 known lamps whose room light stays on (Markdown table).

    python benchmarks/room_light_check.py                     # rooms of radiance 0, 0.15, 0.3, 0.45
    python benchmarks/room_light_check.py --rooms 0.3 --threads 1

:func:`matcap.refine.synthetic.sphere_maps` (48 px) rendered by the fit's own model under
:func:`matcap.refine.synthetic.known_lights` (12 directional lamps, RGB-tinted) in a uniform room of each
radiance, plainly and with three lamps hidden from the left half of the sphere (those photos there show the room's
light alone, as under a cast shadow). The fit is given the lamps' directions only (each photo's intensity fitted)
and starts from :func:`matcap.refine.synthetic.perturb`. Columns: the room's light the start found (``fit.json``
``lights.room_share``), mean normal error in degrees with the default settings, and with the room's light never
kept (``--set lights.room_share=10``), plain / hidden.
"""
from __future__ import annotations

import argparse

import numpy as np


def _errors(rooms: list[float]) -> list[tuple]:
    from matcap.evaluation.metrics import angular_error_map
    from matcap.lightfiles import KnownLights
    from matcap.refine import RefineSettings, refine
    from matcap.refine import synthetic as S
    from scenes.lights import DirectionalLight

    truth = S.sphere_maps(48)
    lights = S.known_lights(12)
    m = truth.mask
    d = np.array([light.direction for light in lights], float)
    known = KnownLights(d / np.linalg.norm(d, axis=1, keepdims=True), None, "file", "room_light_check", "order")
    start = S.perturb(truth)
    rows = []
    for radiance in rooms:
        plain = S.render_capture(truth, lights, ambient=radiance)
        (room,) = S.render_capture(truth, [DirectionalLight((0.0, 0.0, 1.0), (0.0, 0.0, 0.0))], ambient=radiance)
        hidden = [p.copy() for p in plain]
        half = m.shape[1] // 2
        for k in (0, 1, 2):
            hidden[k][:, :half] = room[:, :half]
        row = [radiance]
        for over in ({}, {"lights.room_share": 10.0}):
            for photos in (plain, hidden):
                res = refine(photos, start, RefineSettings(seed=0).replace(over), lights=known)
                if not over and photos is plain:
                    row.append(res.report["lights"]["room_share"])
                row.append(float(angular_error_map(res.maps.normal, truth.normal, m)[m].mean()))
        rows.append(tuple(row))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rooms", default="0,0.15,0.3,0.45", help="the rooms' radiances, comma-separated")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    print("sphere 48 px, 12 known lamps (directions only), a uniform room; normals: mean degrees, plain / three "
          "lamps hidden from half")
    print("| room radiance | room share found | normals | normals, room never kept |")
    print("|---:|---:|---:|---:|")
    for radiance, share, plain, hidden, plain_off, hidden_off in _errors([float(v) for v in args.rooms.split(",")]):
        print(f"| {radiance:g} | {share:.3f} | {plain:.2f} / {hidden:.2f} | {plain_off:.2f} / {hidden_off:.2f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
